"""A second, independent recorder: tetrahedral FEM physics and a triangle rasteriser (issue 25).

    python benchmarks/fem_engine.py benchmarks/scenes/fem_engine/drag.yaml OUT/drag
    python benchmarks/fem_engine.py benchmarks/scenes/fem_engine OUT     # every scene, OUT/<name>

What it is for: recordings of deformable objects made by another simulator and another renderer
than the project's (``mosiv_ros.sim``'s MLS-MPM, ``mosiv_ros.synth.render``'s particle splats),
so that the loop closure (``benchmarks/loop_suite.py``) and ``mosiv run`` can be measured off
their own model. It shares with the project only the rig and the file formats: the scene-file
schema (``mosiv_ros.synth.scene_file``, plus a ``fem`` section), the camera placement
(``mosiv_ros.synth.cameras``), the bag layout (``mosiv_ros.io.bag.write_recording``), the scene
declaration (``mosiv_ros.synth.effects.declaration``) and the ground-truth sidecars
(``mosiv_ros.synth.ground_truth``), whose "particles" are the tets' centroids.
What it is not for: body-body contact (objects must stay apart: an error says when they come
within ``MIN_GAP``), plastic, sand or fluid objects, grippers, or effects other than those below.

Physics (SI units):

- Each object (``sphere`` or ``box``) is a regular lattice of ``fem.cell`` cubes, each cut into
  the 6 Kuhn tetrahedra around its diagonal that points away from the centre; a sphere's lattice is mapped onto the ball
  shell by shell (the shell max|x| = s onto the sphere of radius s, each by the spherified-cube
  map), so its surface nodes lie on the sphere. Linear tets, mass lumped on the nodes (a quarter
  of each tet's mass on each of its nodes).
- Material: stable neo-Hookean (Smith, de Goes, Kim 2018, without the log term),
  Psi = mu/2 (tr F^T F - 3) + (lambda + mu)/2 (J - alpha)^2, alpha = 1 + mu / (lambda + mu),
  whose small-strain limit is linear elasticity with the Lame pair (lambda, mu) of E and nu;
  plus a little mass-proportional (Rayleigh) damping of each node's velocity relative to its
  body's rigid motion, -``fem.damping`` (v - v_cm - w x (x - x_cm)), w from the body's angular
  momentum and inertia: it takes energy from the deformation only, never linear or angular
  momentum (so it is no drag).
- Symplectic Euler with dt = ``fem.cfl`` x (shortest tet altitude) / (P-wave speed) (at most
  ``DAMPING_STEP`` / ``fem.damping``), shortened to a whole number of steps per frame.
- Ground: the plane n . x = height (``floor_tilt`` tilts n), by projection at the nodes: a node
  that the step would take below the plane gets the normal velocity change dv_n that puts it
  on the plane, and Coulomb friction takes up to mu dv_n of its tangential velocity (stopping,
  never reversing, its sliding). mu is the floor's (``floor_friction``, else the project's
  nominal floor).
- Effects, as accelerations at every node: ``gravity`` (g, default (0, 0, -9.81)), ``wind`` (a),
  ``drag`` (-c |v| v, c per object, 1/m), ``linear_drag`` (-k v, k per object, 1/s).

Rendering: every object's boundary triangles and the floor (a square of ``ground.half_size``
cut into triangles of ``FLOOR_CELL``) are rasterised with a z-buffer (per-triangle bounding
boxes, perspective-correct barycentrics): RGB with Lambert shading of flat face normals and a
checker in rest-pose coordinates (``texture_scale`` for the objects, ``FLOOR_CHECKER`` for the
floor), the instance mask (object ids, 0 for the floor and the background) and depth (32FC1
metres along the optical z axis, NaN where nothing is hit), with the scene's ``noise`` added.

Scene files: the project's schema (``mosiv_ros/synth/scene_file.py``) for the objects, ground,
cameras, noise and effects, without its ``simulation`` section (the MPM's), plus::

    fem:                       # optional
      cell: 0.006              # m, lattice cell edge (a sphere's is its diameter / an even count)
      cfl: 0.5                 # time step against the P-wave crossing of the shortest altitude
      damping: 2000            # 1/s, rate of the damping relative to the rigid motion (0: none)
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse
import yaml
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from mosiv_ros.io.bag import write_recording
from mosiv_ros.io.errors import SceneError
from mosiv_ros.io.fields import Fields
from mosiv_ros.io.files import check_new_path
from mosiv_ros.io.recording import Camera, CameraIntrinsics, Frame, Recording
from mosiv_ros.io.scene import Scene, SceneObject, load_yaml, read_scene_text
from mosiv_ros.synth.effects import NOMINAL_GROUND, declaration
from mosiv_ros.synth.ground_truth import GroundTruthParticles, write_ground_truth
from mosiv_ros.synth.scene_file import ObjectSpec, SceneSpec, parse_scene_file

_LOG = logging.getLogger("fem_engine")

GRAVITY = (0.0, 0.0, -9.81)
EFFECTS = ("gravity", "wind", "drag", "linear_drag", "floor_tilt", "floor_friction")
"""Effect types this engine applies; a scene with any other is an error."""
DAMPING_STEP = 0.3
"""Most velocity fraction the damping may take in one step (damping x dt), for stability."""
MIN_GAP = 0.002
"""m: the closest two objects may come (there is no body-body contact)."""
FLOOR_CELL = 0.05
"""m: edge of the floor's rendered triangles' squares."""
FLOOR_CHECKER = 0.1
"""m: side of a floor checker square."""
FLOOR_COLORS = ((165.0, 160.0, 150.0), (95.0, 100.0, 110.0))
BACKGROUND = (20, 24, 32)
LIGHT = np.array([-0.35, 0.5, 1.0]) / np.linalg.norm([-0.35, 0.5, 1.0])
"""Unit direction towards the light (world)."""
AMBIENT = 0.35
CHECKER_DARK = 0.55
"""Brightness of an object's dark checker squares against its colour."""
NEAR = 1e-3
"""m: triangles with a vertex nearer than this to a camera's image plane are not drawn."""
UNITS = {"E": "Pa", "nu": "", "density": "kg/m^3", "friction": "", "ground.friction": "",
         "ground.height": "m", "ground.normal": "", "gravity.g": "m/s^2", "wind.a": "m/s^2",
         "drag.coefficient": "1/m", "linear_drag.coefficient": "1/s"}


@dataclass
class FemSettings:
    """The ``fem`` section of a scene file (see the module docstring)."""

    cell: float = 0.006
    cfl: float = 0.5
    damping: float = 2000.0


def read_scene(path: str | Path) -> tuple[SceneSpec, FemSettings]:
    """The scene file at ``path``: the project's schema plus ``fem`` (SceneError naming the field)."""
    path = Path(path)
    document = load_yaml(read_scene_text(path))
    if not isinstance(document, dict):
        raise SceneError("", "a scene file is a mapping", str(path))
    if "simulation" in document:
        raise SceneError("simulation", "is the MPM recorder's section; this engine reads 'fem'", str(path))
    try:
        fields = Fields(document.pop("fem", None) or {}, "fem")
        settings = FemSettings(fields.number("cell", FemSettings.cell, positive=True),
                               fields.number("cfl", FemSettings.cfl, positive=True),
                               fields.number("damping", FemSettings.damping, lower=0.0))
        fields.done()
    except SceneError as error:
        raise SceneError(error.field, error.problem, str(path)) from None
    spec = parse_scene_file(yaml.safe_dump(document), source=str(path), base_dir=path.parent)
    for i, obj in enumerate(spec.objects):
        if obj.shape not in ("sphere", "box") or obj.family != "elastic":
            raise SceneError(f"objects[{i}]", f"this engine simulates elastic spheres and boxes, "
                             f"not a {obj.family} {obj.shape}", str(path))
    if spec.gripper is not None:
        raise SceneError("gripper", "this engine has no gripper", str(path))
    for i, effect in enumerate(spec.effects):
        if effect.type not in EFFECTS:
            raise SceneError(f"effects[{i}].type", f"this engine applies {', '.join(EFFECTS)}, "
                             f"not {effect.type}", str(path))
    return spec, settings


# ----------------------------------------------------------------------------------------- mesh

@dataclass
class Mesh:
    """A tetrahedral mesh in the body frame: ``nodes`` (N, 3) m, ``tets`` (T, 4) with positive
    volume, ``faces`` (B, 3) boundary triangles ordered so their normals point outwards."""

    nodes: np.ndarray
    tets: np.ndarray
    faces: np.ndarray


def _lattice(counts: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (integer coordinates) and tets: each cube cut into the 6 Kuhn tets around its diagonal
    that points away from the lattice's centre (mirrored octant by octant: the cut stays
    conforming, and a ball mapped from it keeps no slivers at the cube's corners)."""
    n = np.array(counts)
    grid = np.stack(np.meshgrid(*(np.arange(c + 1) for c in counts), indexing="ij"), -1)
    corner = np.stack(np.meshgrid(*(np.arange(c) for c in counts), indexing="ij"), -1).reshape(-1, 3)
    outward = np.where(2 * corner + 1 >= n, 1, -1)
    start = corner + (outward < 0)

    def index(p):
        return (p[:, 0] * (n[1] + 1) + p[:, 1]) * (n[2] + 1) + p[:, 2]

    tets = []
    for order in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        path = [start.copy()]
        for axis in order:
            step = path[-1].copy()
            step[:, axis] += outward[:, axis]
            path.append(step)
        tets.append(np.stack([index(p) for p in path], axis=1))
    return grid.reshape(-1, 3).astype(np.float64), np.concatenate(tets)


def _oriented(nodes: np.ndarray, tets: np.ndarray) -> Mesh:
    """Tets swapped to positive volume (ValueError on a degenerate one) and the boundary faces."""
    edges = nodes[tets[:, 1:]] - nodes[tets[:, :1]]
    volume = np.linalg.det(edges) / 6.0
    if np.any(np.abs(volume) < 1e-12 * np.abs(volume).max()):
        raise ValueError("mesh: a degenerate tetrahedron")
    tets = tets.copy()
    tets[volume < 0, 2:4] = tets[volume < 0, 3:1:-1]
    # face opposite vertex i, ordered so that (b - a) x (c - a) points away from vertex i
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    key = np.sort(faces, axis=1)
    _, inverse, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return Mesh(nodes, tets, faces[count[inverse.ravel()] == 1])


def box_mesh(size: np.ndarray, cell: float) -> Mesh:
    """A box of edge lengths ``size`` centred at the origin, about ``cell`` per lattice cube."""
    counts = tuple(max(1, round(s / cell)) for s in size)
    nodes, tets = _lattice(counts)
    return _oriented(nodes / np.array(counts) * size - size / 2, tets)


def sphere_mesh(radius: float, cell: float) -> Mesh:
    """A ball of ``radius`` about the origin from a lattice of about ``cell`` (an even count across)."""
    n = max(2, 2 * round(radius / cell))
    nodes, tets = _lattice((n, n, n))
    x = nodes / (n / 2) - 1.0  # the cube [-1, 1]^3
    shell = np.abs(x).max(axis=1, keepdims=True)
    u = np.divide(x, shell, out=np.zeros_like(x), where=shell > 0)  # on the unit cube's surface
    u2 = u * u
    # spherified cube: the unit cube's surface onto the unit sphere, evenly
    on_sphere = u * np.sqrt(1.0 - (u2[:, [1, 2, 0]] + u2[:, [2, 0, 1]]) / 2.0
                            + u2[:, [1, 2, 0]] * u2[:, [2, 0, 1]] / 3.0)
    return _oriented(radius * shell * on_sphere, tets)


# -------------------------------------------------------------------------------------- physics

def lame(E: float, nu: float) -> tuple[float, float]:
    """(lambda, mu) of Young's modulus ``E`` (Pa) and Poisson's ratio ``nu``."""
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


@dataclass
class Body:
    """One object's mesh placed in the world, its material and its initial motion."""

    mesh: Mesh
    rest_world: np.ndarray
    velocity: np.ndarray
    E: float
    nu: float
    density: float


def place(obj: ObjectSpec, settings: FemSettings) -> Body:
    """The object of a scene file as a FEM body: its shape meshed, posed, moving as given."""
    mesh = (sphere_mesh(obj.size["radius"], settings.cell) if obj.shape == "sphere"
            else box_mesh(np.asarray(obj.size["size"], dtype=np.float64), settings.cell))
    rotation = Rotation.from_quat(obj.orientation).as_matrix()
    offset = mesh.nodes @ rotation.T
    velocity = obj.velocity + np.cross(obj.angular_velocity, offset)
    return Body(mesh, offset + obj.position, velocity, obj.params["E"], obj.params["nu"],
                obj.params["density"])


class Fem:
    """Several elastic bodies on one floor under body accelerations, stepped explicitly.

    ``x``, ``v`` (N, 3) are every body's nodes, body after body (``body_of`` (N,) says whose);
    the floor is ``normal . x = height`` with Coulomb ``friction``; ``gravity`` and ``wind``
    (3,) m/s^2, ``drag`` (1/m) and ``linear_drag`` (1/s) per body.
    """

    def __init__(self, bodies: list[Body], *, gravity=GRAVITY, wind=(0.0, 0.0, 0.0), drag=None,
                 linear_drag=None, floor_normal=(0.0, 0.0, 1.0), floor_height: float = 0.0,
                 friction: float = NOMINAL_GROUND.friction, settings: FemSettings | None = None):
        settings = settings or FemSettings()
        offsets = np.cumsum([0] + [len(b.rest_world) for b in bodies])
        self.x = np.concatenate([b.rest_world for b in bodies]).astype(np.float64)
        self.v = np.concatenate([b.velocity for b in bodies]).astype(np.float64)
        self.body_of = np.repeat(np.arange(len(bodies)), np.diff(offsets))
        self.tets = np.concatenate([b.mesh.tets + o for b, o in zip(bodies, offsets, strict=False)])
        tet_body = np.repeat(np.arange(len(bodies)), [len(b.mesh.tets) for b in bodies])
        edges = (self.x[self.tets[:, 1:]] - self.x[self.tets[:, :1]]).transpose(0, 2, 1)  # columns
        self.rest_volume = np.linalg.det(edges) / 6.0
        lam, mu = np.array([lame(b.E, b.nu) for b in bodies]).T
        density = np.array([b.density for b in bodies])
        self.mu, self.lam = mu[tet_body], lam[tet_body]
        self.damping = settings.damping
        self._bodies = [slice(a, b) for a, b in zip(offsets[:-1], offsets[1:], strict=True)]
        # The shape functions' gradients: F's column j of tet t = sum_a x_a B[t, a, j], as one
        # sparse operator from node positions (N, 3) to the columns (3 T, 3), row j T + t.
        count = len(self.tets)
        B = np.linalg.inv(edges)  # rows: gradients of the shape functions of corners 1..3
        B = np.concatenate([-B.sum(axis=1, keepdims=True), B], axis=1)  # (T, 4, 3)
        rows = np.arange(3)[:, None, None] * count + np.arange(count)[None, :, None]
        self._gradient = scipy.sparse.csr_matrix(
            (B.transpose(2, 0, 1).ravel(), (np.broadcast_to(rows, (3, count, 4)).ravel(),
                                            np.broadcast_to(self.tets, (3, count, 4)).ravel())),
            shape=(3 * count, len(self.x)))
        self._divergence = self._gradient.T.tocsr()
        self.mass = np.bincount(self.tets.ravel(), np.repeat(density[tet_body] * self.rest_volume / 4.0, 4),
                                minlength=len(self.x))
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.wind = np.asarray(wind, dtype=np.float64)
        self.drag = np.zeros(len(bodies)) if drag is None else np.asarray(drag, dtype=np.float64)
        self.linear_drag = np.zeros(len(bodies)) if linear_drag is None else np.asarray(linear_drag, np.float64)
        normal = np.asarray(floor_normal, dtype=np.float64)
        self.normal, self.height, self.friction = normal / np.linalg.norm(normal), floor_height, friction
        # shortest altitude 3 V / (largest face area), P-wave speed
        corners = self.x[self.tets]
        areas = np.stack([np.linalg.norm(np.cross(corners[:, b] - corners[:, a], corners[:, c] - corners[:, a]),
                                         axis=1) / 2 for a, b, c in ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))])
        altitude = float(np.min(3 * self.rest_volume / areas.max(axis=0)))
        speed = float(np.max(np.sqrt((lam + 2 * mu) / density)))
        self.dt = min(settings.cfl * altitude / speed, DAMPING_STEP / max(self.damping, 1e-30))

    def columns(self, x: np.ndarray) -> np.ndarray:
        """The tets' deformation gradients at node positions ``x`` as columns: (3, T, 3), [j, t] = F_t e_j.

        Of node velocities, the same gives the rates of F.
        """
        return (self._gradient @ x).reshape(3, len(self.tets), 3)

    def elastic_energy(self) -> float:
        """Stored energy (J) of the stable neo-Hookean material at the current positions."""
        f0, f1, f2 = self.columns(self.x)
        lam_s = self.lam + self.mu
        J = np.einsum("ti,ti->t", f0, _cross(f1, f2))
        psi = self.mu / 2 * ((f0 * f0 + f1 * f1 + f2 * f2).sum(axis=1) - 3) + lam_s / 2 * (J - 1 - self.mu / lam_s) ** 2
        psi0 = lam_s / 2 * (self.mu / lam_s) ** 2  # Psi(I), so that the rest state holds none
        return float(np.sum(self.rest_volume * (psi - psi0)))

    def internal_forces(self) -> np.ndarray:
        """Node forces (N, 3) N of the material's stress: -sum over tets of V0 P B."""
        F = self.columns(self.x)
        cofactor = np.stack([_cross(F[1], F[2]), _cross(F[2], F[0]), _cross(F[0], F[1])])
        J = np.einsum("ti,ti->t", F[0], cofactor[0])
        lam_s = self.lam + self.mu
        P = self.mu[:, None] * F + (lam_s * (J - 1 - self.mu / lam_s))[:, None] * cofactor
        return self._divergence @ (-self.rest_volume[:, None] * P).reshape(-1, 3)

    def rigid_velocities(self) -> np.ndarray:
        """(N, 3): each node's velocity were its body moving rigidly with its momenta."""
        rigid = np.empty_like(self.v)
        for part in self._bodies:
            m, x, v = self.mass[part, None], self.x[part], self.v[part]
            centre = (m * x).sum(axis=0) / m.sum()
            r = x - centre
            inertia = np.eye(3) * (m * r * r).sum() - (m * r).T @ r
            spin = np.linalg.solve(inertia, (m * np.cross(r, v)).sum(axis=0))
            rigid[part] = (m * v).sum(axis=0) / m.sum() + np.cross(spin, r)
        return rigid

    def accelerations(self) -> np.ndarray:
        """Node accelerations (N, 3) off the floor: material, damping and effects."""
        a = self.internal_forces() / self.mass[:, None] + self.gravity + self.wind
        if self.damping > 0:
            a -= self.damping * (self.v - self.rigid_velocities())
        speed = np.linalg.norm(self.v, axis=1, keepdims=True)
        a -= (self.drag[self.body_of, None] * speed + self.linear_drag[self.body_of, None]) * self.v
        return a

    def step(self) -> None:
        """One symplectic Euler step of ``dt``, the floor's projection and friction at its end."""
        self.v += self.dt * self.accelerations()
        depth = self.height - (self.x + self.dt * self.v) @ self.normal
        touching = np.flatnonzero(depth > 0)
        if touching.size:
            v = self.v[touching]
            v_n = v @ self.normal
            sliding = v - v_n[:, None] * self.normal
            slide = np.linalg.norm(sliding, axis=1)
            push = depth[touching] / self.dt
            keep = np.maximum(1.0 - self.friction * push / np.maximum(slide, 1e-12), 0.0)
            self.v[touching] = keep[:, None] * sliding + (v_n + push)[:, None] * self.normal
        self.x += self.dt * self.v

    def run(self, n_frames: int, frame_dt: float) -> np.ndarray:
        """Node positions (n_frames + 1, N, 3) at the frames, stepping a whole number of steps each."""
        steps = math.ceil(frame_dt / self.dt)
        self.dt = frame_dt / steps
        positions = [self.x.copy()]
        for _ in range(n_frames):
            for _ in range(steps):
                self.step()
            if not np.all(np.isfinite(self.x)):
                raise FloatingPointError(f"the FEM diverged by frame {len(positions)} (dt {self.dt:.3g} s)")
            positions.append(self.x.copy())
        return np.stack(positions)


def scene_fem(spec: SceneSpec, settings: FemSettings) -> tuple[Fem, list[Body]]:
    """The scene's bodies and their FEM with the scene's effects (undeclared ones included)."""
    bodies = [place(obj, settings) for obj in spec.objects]
    names = [obj.name for obj in spec.objects]
    values = {effect.type: effect.params for effect in spec.effects}

    def per_body(kind: str):
        return [values[kind]["coefficient"][name] for name in names] if kind in values else None

    fem = Fem(bodies, gravity=values.get("gravity", {}).get("g", GRAVITY),
              wind=values.get("wind", {}).get("a", (0.0, 0.0, 0.0)), drag=per_body("drag"),
              linear_drag=per_body("linear_drag"),
              floor_normal=values.get("floor_tilt", {}).get("normal", NOMINAL_GROUND.normal),
              floor_height=spec.ground.height,
              friction=values.get("floor_friction", {}).get("friction", NOMINAL_GROUND.friction),
              settings=settings)
    below = np.flatnonzero(fem.x @ fem.normal < fem.height)
    if below.size:
        raise SceneError(f"objects[{fem.body_of[below[0]]}].position", "starts below the floor", spec.source)
    return fem, bodies


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (T, 3) arrays (np.cross costs more at this size)."""
    return a[:, [1, 2, 0]] * b[:, [2, 0, 1]] - a[:, [2, 0, 1]] * b[:, [1, 2, 0]]


def check_apart(positions: np.ndarray, body_of: np.ndarray, names: list[str]) -> None:
    """ValueError when two bodies come within MIN_GAP at a frame (this engine has no body contact)."""
    for frame, x in enumerate(positions):
        for i in range(len(names)):
            tree = cKDTree(x[body_of == i])
            for j in range(i + 1, len(names)):
                gap = tree.query(x[body_of == j])[0].min()
                if gap < MIN_GAP:
                    raise ValueError(f"{names[i]} and {names[j]} come within {gap * 1e3:.1f} mm at frame {frame}: "
                                     "this engine has no contact between bodies; set them further apart")


# ------------------------------------------------------------------------------------ rendering

def rasterise(intrinsics: CameraIntrinsics, T_world_optical: np.ndarray, vertices: np.ndarray,
              triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest triangle per pixel: (depth (H*W,) m along optical z, inf where none; its index
    (H*W,), -1 where none; perspective-correct barycentrics (H*W, 3)), row-major pixels.

    A triangle is drawn where a pixel centre lies inside its projection (edges included);
    triangles with a vertex within ``NEAR`` of the image plane or behind it are skipped.
    """
    R, t = T_world_optical[:3, :3], T_world_optical[:3, 3]
    w, h = intrinsics.width, intrinsics.height
    K = intrinsics.K
    depth = np.full(w * h, np.inf)
    owner = np.full(w * h, -1, dtype=np.int64)
    bary = np.zeros((w * h, 3))
    local = (vertices - t) @ R
    z = local[:, 2]
    drawn = np.flatnonzero(np.all(z[triangles] > NEAR, axis=1))
    if drawn.size == 0:
        return depth, owner, bary
    screen = local[:, :2] / np.where(z > NEAR, z, 1.0)[:, None] * K[[0, 1], [0, 1]] + K[[0, 1], [2, 2]]
    corners = screen[triangles[drawn]]  # (D, 3, 2)
    lo = np.maximum(np.ceil(corners.min(axis=1)), 0).astype(np.int64)
    hi = np.minimum(np.floor(corners.max(axis=1)), [w - 1, h - 1]).astype(np.int64)
    span = np.maximum(hi - lo + 1, 0)
    count = span[:, 0] * span[:, 1]
    which = np.repeat(np.arange(drawn.size), count)
    rank = np.arange(which.size) - np.repeat(np.cumsum(count) - count, count)
    u = lo[which, 0] + rank % span[which, 0]
    v = lo[which, 1] + rank // span[which, 0]
    a, b, c = (corners[which, k] for k in range(3))
    p = np.stack([u, v], axis=1).astype(np.float64)

    def cross(e, f):
        return e[:, 0] * f[:, 1] - e[:, 1] * f[:, 0]

    area = cross(b - a, c - a)
    with np.errstate(divide="ignore", invalid="ignore"):
        w0, w1 = cross(b - p, c - p) / area, cross(c - p, a - p) / area
    weights = np.stack([w0, w1, 1.0 - w0 - w1], axis=1)
    inside = (np.abs(area) > 1e-12) & np.all(weights >= -1e-9, axis=1)
    which, u, v, weights = which[inside], u[inside], v[inside], weights[inside]
    over_z = weights / z[triangles[drawn[which]]]
    inverse_depth = over_z.sum(axis=1)
    s = 1.0 / inverse_depth
    pixel = v * w + u
    order = np.lexsort((s, pixel))
    first = order[np.r_[True, pixel[order][1:] != pixel[order][:-1]]]
    depth[pixel[first]] = s[first]
    owner[pixel[first]] = drawn[which[first]]
    bary[pixel[first]] = over_z[first] / inverse_depth[first, None]
    return depth, owner, bary


@dataclass
class Surfaces:
    """Everything to draw at one instant: triangles over ``vertices`` (V, 3) world, each with a
    mask ``label``, a light and a dark ``colors`` (T, 2, 3) and a checker side ``checker`` (T,)
    (inf: plain) over the vertices' texture coordinates ``texture`` (V, 3) m."""

    vertices: np.ndarray
    triangles: np.ndarray
    label: np.ndarray
    colors: np.ndarray
    checker: np.ndarray
    texture: np.ndarray


def floor_surfaces(normal: np.ndarray, height: float, half_size: float) -> Surfaces:
    """The floor's square of ``half_size`` on the plane normal . x = height, as triangles."""
    normal = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    e1 = np.cross([0.0, 1.0, 0.0], normal)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    n = max(1, round(2 * half_size / FLOOR_CELL))
    a, b = np.meshgrid(np.linspace(-half_size, half_size, n + 1), np.linspace(-half_size, half_size, n + 1),
                       indexing="ij")
    plane = np.stack([a.ravel(), b.ravel()], axis=1)
    vertices = height * normal + plane[:, :1] * e1 + plane[:, 1:] * e2
    i, j = (k.ravel() for k in np.meshgrid(np.arange(n), np.arange(n), indexing="ij"))
    corner = i * (n + 1) + j
    triangles = np.concatenate([np.stack([corner, corner + n + 1, corner + n + 2], 1),
                                np.stack([corner, corner + n + 2, corner + 1], 1)])
    count = len(triangles)
    return Surfaces(vertices, triangles, np.zeros(count, dtype=np.int64),
                    np.broadcast_to(np.array(FLOOR_COLORS), (count, 2, 3)), np.full(count, FLOOR_CHECKER),
                    np.concatenate([plane, np.zeros((len(plane), 1))], axis=1))


def body_surfaces(bodies: list[Body], objects: list[ObjectSpec], x: np.ndarray) -> Surfaces:
    """The bodies' boundary triangles at node positions ``x`` (N, 3), textured in rest pose."""
    triangles, labels, colors, checker = [], [], [], []
    offset = 0
    for body, obj in zip(bodies, objects, strict=True):
        triangles.append(body.mesh.faces + offset)
        count = len(body.mesh.faces)
        labels.append(np.full(count, obj.id))
        colors.append(np.tile([obj.color, CHECKER_DARK * obj.color], (count, 1, 1)))
        checker.append(np.full(count, obj.texture_scale if obj.texture == "checker" else np.inf))
        offset += len(body.mesh.nodes)
    return Surfaces(x, np.concatenate(triangles), np.concatenate(labels), np.concatenate(colors),
                    np.concatenate(checker), np.concatenate([b.mesh.nodes for b in bodies]))


def render(intrinsics: CameraIntrinsics, T_world_optical: np.ndarray,
           parts: list[Surfaces]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb (H, W, 3) uint8, mask (H, W) uint8 or uint16, depth (H, W) float32 NaN where empty)."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
    vertices = np.concatenate([p.vertices for p in parts])
    triangles = np.concatenate([p.triangles + o for p, o in zip(parts, offsets, strict=False)])
    label = np.concatenate([p.label for p in parts])
    depth, owner, bary = rasterise(intrinsics, T_world_optical, vertices, triangles)
    hit = owner >= 0
    tri = owner[hit]
    corners = vertices[triangles[tri]]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    texture = np.einsum("pk,pkj->pj", bary[hit], np.concatenate([p.texture for p in parts])[triangles[tri]])
    checker = np.concatenate([p.checker for p in parts])[tri]
    dark = (np.floor(texture / checker[:, None]).sum(axis=1) % 2 == 1).astype(np.int64)
    albedo = np.concatenate([p.colors for p in parts])[tri, dark]
    light = AMBIENT + (1 - AMBIENT) * np.clip(normal @ LIGHT, 0.0, None)
    rgb = np.tile(np.array(BACKGROUND, dtype=np.float64), (depth.size, 1))
    rgb[hit] = albedo * light[:, None]
    mask = np.zeros(depth.size, dtype=np.uint8 if label.max(initial=0) <= 255 else np.uint16)
    mask[hit] = label[tri]
    h, w = intrinsics.height, intrinsics.width
    return (np.clip(rgb.round(), 0, 255).astype(np.uint8).reshape(h, w, 3), mask.reshape(h, w),
            np.where(hit, depth, np.nan).astype(np.float32).reshape(h, w))


# ------------------------------------------------------------------------------------ recording

def record(spec: SceneSpec, settings: FemSettings, out: str | Path, *, seed: int = 0) -> Path:
    """Simulate, render and write ``spec`` as a new bag directory ``out`` with its sidecars."""
    check_new_path(out)
    start = time.perf_counter()
    fem, bodies = scene_fem(spec, settings)
    steps = math.ceil(1.0 / spec.cameras.fps / fem.dt)
    _LOG.info("%s: %d nodes, %d tets, %d frames x %d steps", spec.name, len(fem.x), len(fem.tets),
              spec.n_frames, steps)
    positions = fem.run(spec.n_frames, 1.0 / spec.cameras.fps)
    simulated = time.perf_counter() - start
    check_apart(positions, fem.body_of, [o.name for o in spec.objects])
    rng = np.random.default_rng(seed)
    cams = spec.cameras
    floor = floor_surfaces(fem.normal, fem.height, spec.ground.half_size)
    frames: dict[str, list[Frame]] = {name: [] for name in cams.names}
    for k, x in enumerate(positions):
        parts = [floor, body_surfaces(bodies, spec.objects, x)]
        for name, pose in zip(cams.names, cams.poses, strict=True):
            rgb, mask, depth = render(cams.intrinsics, pose, parts)
            if spec.noise.rgb_std > 0:
                rgb = np.clip(rgb + rng.normal(0, spec.noise.rgb_std, rgb.shape), 0, 255).round().astype(np.uint8)
            if spec.noise.depth_std > 0:
                depth = (depth + rng.normal(0, spec.noise.depth_std, depth.shape)).astype(np.float32)
            frames[name].append(Frame(spec.stamp_ns(k), rgb, mask, depth if cams.depth else None))
    ground, effects = declaration(spec.effects, spec.ground.height)
    scene = Scene(objects=[SceneObject(o.id, o.name, o.family if o.declared_family else None,
                                       {p: o.params[p] for p in o.declared_params}) for o in spec.objects],
                  ground=ground, effects=effects)
    cameras = {name: Camera(name, cams.intrinsics, pose, frames[name])
               for name, pose in zip(cams.names, cams.poses, strict=True)}
    path = write_recording(Recording(cameras, scene), out, compress=True)
    centroids = positions[:, fem.tets].mean(axis=2)
    particles = GroundTruthParticles(
        positions=centroids, object_id=np.array([spec.objects[b].id for b in fem.body_of[fem.tets[:, 0]]]),
        volume=fem.rest_volume, stamps_ns=np.array([spec.stamp_ns(k) for k in range(len(positions))]),
        times=np.arange(len(positions)) / cams.fps)
    write_ground_truth(path, truth_document(spec, settings, fem, bodies, seed, simulated), particles)
    _LOG.info("%s: recorded %s (simulated in %.1f s, %.1f s in all)", spec.name, path, simulated,
              time.perf_counter() - start)
    return path


def truth_document(spec: SceneSpec, settings: FemSettings, fem: Fem, bodies: list[Body], seed: int,
                   simulated_s: float) -> dict[str, Any]:
    """ground_truth.yaml's content, in the project's format (``mosiv_ros.synth.ground_truth``)."""
    cams = spec.cameras
    return {
        "scene": spec.name, "scene_file": spec.source, "seed": seed,
        "frames": {"count": spec.n_frames + 1, "fps": cams.fps, "start_stamp_ns": spec.start_stamp_ns},
        "units": UNITS,
        "objects": [{"id": o.id, "name": o.name, "family": o.family, "params": o.params,
                     "declared_params": o.declared_params, "declared_family": o.declared_family,
                     "shape": o.shape, "size": o.size, "position": o.position, "orientation": o.orientation,
                     "velocity": o.velocity, "angular_velocity": o.angular_velocity, "color": o.color,
                     "texture": o.texture, "nodes": len(b.mesh.nodes), "tets": len(b.mesh.tets)}
                    for o, b in zip(spec.objects, bodies, strict=True)],
        "effects": [effect.ground_truth() for effect in spec.effects],
        "ground": {"height": fem.height, "normal": fem.normal.tolist(), "friction": fem.friction,
                   "half_size": spec.ground.half_size},
        "gripper": None,
        "cameras": {"names": cams.names, "placement": cams.placement, "width": cams.intrinsics.width,
                    "height": cams.intrinsics.height, "K": cams.intrinsics.K, "depth": cams.depth,
                    "T_world_optical": dict(zip(cams.names, cams.poses, strict=True))},
        "noise": {"rgb_std": spec.noise.rgb_std, "depth_std": spec.noise.depth_std},
        "simulation": {"engine": "benchmarks/fem_engine.py", "model": "stable neo-Hookean, linear tets, "
                       "lumped mass, symplectic Euler, penalty floor with Coulomb friction",
                       "cell": settings.cell, "cfl": settings.cfl, "damping": settings.damping,
                       "dt": fem.dt,
                       "steps_per_frame": round(1.0 / cams.fps / fem.dt), "seconds": simulated_s},
        "render": {"renderer": "benchmarks/fem_engine.py", "surface": "the tets' boundary triangles, "
                   "z-buffered; particles_file holds the tets' centroids with their rest volumes"},
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="a scene file, or a folder: each of its *.yaml")
    parser.add_argument("out", type=Path, help="the new bag directory; for a folder, the parent of one per scene")
    parser.add_argument("--seed", type=int, default=0, help="seed of the pixel noise")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    if args.scene.is_dir():
        jobs = [(path, args.out / path.stem) for path in sorted(args.scene.glob("*.yaml"))]
    else:
        jobs = [(args.scene, args.out)]
    for scene, out in jobs:
        try:
            record(*read_scene(scene), out, seed=args.seed)
        except (SceneError, ValueError, FloatingPointError) as error:
            print(f"fem_engine: {scene}: {error}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
