"""Boundary conditions on the grid: the ground plane, the domain walls, kinematic colliders.

All three project grid velocities in the grid update (``kernels.grid_update``), after the
accelerations of the effects and the contact between objects:

- **Ground**: a plane n . x = height with Coulomb friction. At nodes below the plane, a velocity
  moving into it loses its normal part, and its tangential part shrinks by friction * |normal
  part|, stopping when that is larger (Stomakhin et al. 2013, Sec. 8). Height, normal (a tilted
  floor) and friction are differentiable parameters ``ground.*``.
- **Walls**: the faces of the simulation domain; velocities into a wall vanish within
  ``WALL_CELLS`` nodes of it (slip walls).
- **Colliders**: a sphere, box or capsule moving rigidly along a known 6-DoF pose trajectory
  (a gripper or finger: the M-PhyGs contact-point boundary condition, Sec. B, imposed on the grid
  rather than by overwriting particle velocities). At nodes inside the collider, the velocity
  relative to the collider's own velocity (v_c + omega x r) gets the same Coulomb projection.

What it is not for: forces (``effects``) or contact between simulated objects (``kernels``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mosiv_ros.io.transforms import pose_at, segment
from mosiv_ros.sim.params import ParamSpec

WALL_CELLS = 3
COLLIDER_SHAPES = {"sphere": 0, "box": 1, "capsule": 2}
GROUND_FRICTION = 0.5
"""Coulomb coefficient of a ground whose friction nobody gives (the fit's starting value)."""

GROUND_PARAMS = (
    ParamSpec("ground.height", 0.0, -1.0e3, 1.0e3, "m", "ground plane offset along its normal"),
    ParamSpec("ground.normal", (0.0, 0.0, 1.0), -1.0, 1.0, "", "ground plane normal (normalised "
              "in the kernel)", size=3),
    ParamSpec("ground.friction", GROUND_FRICTION, 0.0, 5.0, "", "Coulomb coefficient of the ground"),
)


@dataclass
class Ground:
    """Initial values of the ground plane's parameters (all three can then be fitted)."""

    height: float = 0.0
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    friction: float = GROUND_FRICTION

    def initial(self) -> dict[str, object]:
        return {"ground.height": self.height, "ground.normal": self.normal,
                "ground.friction": self.friction}


@dataclass
class Collider:
    """A rigid kinematic collider following a pose trajectory.

    ``shape``: 'sphere' (``size`` = (radius,)), 'box' (half extents (hx, hy, hz)) or 'capsule'
    (radius, half length along its local z axis). ``times`` (T,) seconds, ``positions`` (T, 3)
    metres and ``quaternions`` (T, 4) x, y, z, w (world from collider) give the trajectory,
    linearly interpolated (slerp for rotations) and held constant outside it.
    """

    shape: str
    size: tuple[float, ...]
    times: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray | None = None
    friction: float = 0.5
    name: str = "collider"
    _q: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.shape not in COLLIDER_SHAPES:
            raise ValueError(f"collider {self.name!r}: unknown shape {self.shape!r} "
                             f"(expected one of {', '.join(COLLIDER_SHAPES)})")
        need = {"sphere": 1, "box": 3, "capsule": 2}[self.shape]
        size = tuple(float(s) for s in np.atleast_1d(self.size))
        if len(size) != need or min(size) <= 0:
            raise ValueError(f"collider {self.name!r}: a {self.shape} needs {need} positive size "
                             f"value(s), got {self.size}")
        self.size = size
        self.times = np.asarray(self.times, dtype=np.float64).ravel()
        self.positions = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)
        if len(self.times) == 0 or len(self.positions) != len(self.times):
            raise ValueError(f"collider {self.name!r}: times and positions must have the same, "
                             f"non-zero length ({len(self.times)} vs {len(self.positions)})")
        if np.any(np.diff(self.times) <= 0):
            raise ValueError(f"collider {self.name!r}: times must increase strictly")
        if self.quaternions is None:
            q = np.tile([0.0, 0.0, 0.0, 1.0], (len(self.times), 1))
        else:
            q = np.asarray(self.quaternions, dtype=np.float64).reshape(-1, 4)
            if len(q) != len(self.times):
                raise ValueError(f"collider {self.name!r}: {len(q)} quaternions for "
                                 f"{len(self.times)} times")
            q = q / np.linalg.norm(q, axis=1, keepdims=True)
            # Keep consecutive quaternions in one hemisphere so that slerp takes the short way.
            for i in range(1, len(q)):
                if np.dot(q[i], q[i - 1]) < 0:
                    q[i] = -q[i]
        self._q = q
        if not 0.0 <= self.friction <= 5.0:
            raise ValueError(f"collider {self.name!r}: friction {self.friction} outside [0, 5]")

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Position (3,) and unit quaternion (x, y, z, w) at time t."""
        return pose_at(self.times, self.positions, self._q, t)

    def velocity(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Linear (3,) and angular (3,) velocity in world, constant over each segment."""
        if len(self.times) < 2 or t < self.times[0] or t >= self.times[-1]:
            return np.zeros(3), np.zeros(3)
        i, _ = segment(self.times, t)
        dt = self.times[i + 1] - self.times[i]
        linear = (self.positions[i + 1] - self.positions[i]) / dt
        # omega from the relative rotation q_{i+1} q_i^-1 = (axis sin(theta/2), cos(theta/2))
        rel = _qmul(self._q[i + 1], _qconj(self._q[i]))
        if rel[3] < 0:
            rel = -rel
        sin_half = np.linalg.norm(rel[:3])
        angle = 2.0 * np.arctan2(sin_half, rel[3])
        axis = rel[:3] / sin_half if sin_half > 1e-12 else np.zeros(3)
        return linear, axis * angle / dt


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def _qconj(q: np.ndarray) -> np.ndarray:
    return np.array([-q[0], -q[1], -q[2], q[3]])
