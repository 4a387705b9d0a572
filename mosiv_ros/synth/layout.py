"""A parsed scene file laid out at t = 0: particles, floor, gripper, and the geometric checks.

What it is for: turning a ``SceneSpec`` into what the simulator and the renderer start from
(every object's particles with velocities, volumes and colours, the simulated floor, the
gripper's collider), and rejecting what only geometry reveals: objects overlapping each other
or the gripper at t = 0, objects reaching below the floor, cameras that see no object. Errors
are ``SceneError`` naming the scene file and the field.
What it is not for: running the simulation or rendering (``recorder``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation

from mosiv_ros.io.errors import SceneError
from mosiv_ros.sim import Collider, Ground
from mosiv_ros.synth.bodies import Body, gripper_contains
from mosiv_ros.synth.effects import simulator_ground
from mosiv_ros.synth.scene_file import MAX_PARTICLES, SceneSpec

_LOG = logging.getLogger(__name__)


@dataclass
class Layout:
    """The scene at t = 0: ``bodies`` in mask-id order, the simulated ``ground``, the collider."""

    spec: SceneSpec
    bodies: list[Body]
    ground: Ground
    collider: Collider | None

    @cached_property
    def x(self) -> np.ndarray:
        """All particle positions (N, 3), object after object."""
        return np.concatenate([body.x for body in self.bodies])

    @cached_property
    def v(self) -> np.ndarray:
        """All initial particle velocities (N, 3)."""
        return np.concatenate([body.v for body in self.bodies])

    @cached_property
    def object_index(self) -> np.ndarray:
        """Index (N,) of each particle's object, 0..K-1 (its mask id minus one)."""
        return np.concatenate([np.full(len(b.rest), k) for k, b in enumerate(self.bodies)])

    @cached_property
    def volume(self) -> np.ndarray:
        """Particle volumes (N,), m^3."""
        return np.concatenate([np.full(len(b.rest), b.volume) for b in self.bodies])

    @cached_property
    def albedo(self) -> np.ndarray:
        """Particle colours (N, 3), 0..255."""
        return np.concatenate([body.albedo for body in self.bodies])


def lay_out(spec: SceneSpec) -> Layout:
    """Lay ``spec`` out at t = 0 and check it; SceneError names ``spec.source`` and the field."""
    try:
        return _lay_out(spec)
    except SceneError as exc:
        raise SceneError(exc.field, exc.problem, spec.source) from None


def _lay_out(spec: SceneSpec) -> Layout:
    spacing = spec.simulation.particle_spacing
    bodies: list[Body] = []
    for i, obj in enumerate(spec.objects):  # each refused before it is allocated past the limit
        budget = MAX_PARTICLES - sum(len(body.rest) for body in bodies)
        bodies.append(Body.sample(obj, spacing, f"objects[{i}]", budget))
    ground = simulator_ground(spec.effects, spec.ground.height)
    normal = np.asarray(ground.normal) / np.linalg.norm(ground.normal)
    for i, body in enumerate(bodies):
        depth = ground.height - float(np.min(body.x @ normal))
        if depth > 0:
            raise SceneError(f"objects[{i}].position",
                             f"{body.spec.name!r} reaches {depth:.3g} m below the floor at t = 0")
    for j, later in enumerate(bodies):
        for i, earlier in enumerate(bodies[:j]):
            inside = int(earlier.contains(later.x).sum() + later.contains(earlier.x).sum())
            if inside:
                raise SceneError(f"objects[{j}].position",
                                 f"{later.spec.name!r} overlaps objects[{i}] ({earlier.spec.name!r}) at "
                                 f"t = 0: {inside} particles lie inside the other object")
    collider = None
    if spec.gripper is not None:
        g = spec.gripper
        collider = Collider(g.shape, g.size, g.times, g.positions, g.orientations, g.friction, "gripper")
        position, quaternion = collider.pose(0.0)
        local = (np.concatenate([b.x for b in bodies]) - position) @ Rotation.from_quat(quaternion).as_matrix()
        if gripper_contains(g, local).any():
            raise SceneError("gripper.trajectory", "the gripper overlaps an object at t = 0")
    layout = Layout(spec, bodies, ground, collider)
    _check_cameras(spec, layout.x)
    _LOG.info("laid out %s: %d objects, %d particles", spec.name, len(bodies), len(layout.x))
    return layout


def _check_cameras(spec: SceneSpec, x: np.ndarray) -> None:
    cams = spec.cameras
    k = cams.intrinsics
    for index, (name, T) in enumerate(zip(cams.names, cams.poses, strict=True)):
        uv = k.project((x - T[:3, 3]) @ T[:3, :3])
        with np.errstate(invalid="ignore"):
            seen = (uv[:, 0] >= -0.5) & (uv[:, 0] < k.width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < k.height - 0.5)
        if not seen.any():
            where = f"cameras.poses[{index}]" if cams.placement == "explicit" else "cameras"
            raise SceneError(where, f"camera {name!r} sees none of the objects at t = 0 "
                             "(check its position, look_at and field of view)")
