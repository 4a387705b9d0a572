"""The scene declaration and the lifted particles in the simulator's terms.

What it is for: the one translation from what a scene declares and lifting gives (``io.scene``,
``lifting``) to the simulator's inputs (``mosiv_ros.sim``), shared by the fit
(``identify.problem``) and the twin (``predict.twin``): ``to_sim_particles`` (positions, M-PhyGs
volumes for the boundary offsets o_s tried, object index 0..K-1), ``ground_of`` (the declared
ground plane), ``effects_of`` (gravity and the declared simulator effects), ``colliders_of`` (the
declared gripper along its recorded poses), ``declared_params``
(an object's declared parameters in the simulator's names and units) and ``OFFSET``, the name
the boundary offset goes by among an object's parameters.
What it is not for: lifting itself, choosing the offsets or the free parameters
(``identify.problem``).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from mosiv_ros.io.scene import Scene, SceneObject
from mosiv_ros.lifting.lift import LiftedParticles
from mosiv_ros.sim import BUILTIN_EFFECTS, Collider, Gravity, Ground, ObjectModel, Particles
from mosiv_ros.sim.materials import in_sim_units

_LOG = logging.getLogger(__name__)

OFFSET = "boundary_offset"
"""The name of an object's boundary offset o_s among its parameters (not a simulator parameter)."""
DEFAULT_GRAVITY = (0.0, 0.0, -9.81)
"""m/s^2: gravity where the scene declares no ``gravity`` effect (DESIGN.md)."""
SENSOR_EFFECTS = ("camera_time_offset", "mask_noise")
"""Declared effects that act on the observations, not on the simulated motion."""


def to_sim_particles(lifted: LiftedParticles,
                     offsets: Mapping[int, float] | None = None) -> tuple[Particles, list[int]]:
    """(Particles, object ids) for the simulator, with boundary offsets o_s per segment.

    A particle's object index is its id's position in the returned list (ids in increasing
    order); volumes are V_i = V_g (sigmoid(-beta (d_i + o_s)) + eps).
    """
    ids = lifted.object_ids
    index = np.searchsorted(np.asarray(ids), lifted.object_id)
    return Particles(lifted.x, lifted.volumes(offsets), index), ids


def declared_params(item: SceneObject | None) -> dict[str, float]:
    """An object's declared parameters in the simulator's names and units (friction angle in rad)."""
    return in_sim_units(item.params if item is not None else {})


def ground_of(scene: Scene) -> Ground | None:
    """The declared ground plane (the simulator's default friction unless declared), or None."""
    if scene.ground is None:
        return None
    height, normal = scene.ground.plane()
    friction = scene.ground.friction
    return Ground(height=height, normal=normal, friction=Ground.friction if friction is None else friction)


def colliders_of(scene: Scene, poses: Sequence[tuple[int, np.ndarray]], start_ns: int) -> list[Collider]:
    """The declared gripper as a collider along ``poses`` ((stamp_ns, T_world_gripper), in order).

    Times are seconds after ``start_ns``; before the first pose and after the last the gripper
    holds still there (``sim.Collider``). Empty without a declared gripper; a declared gripper
    without poses is left out with a warning (nothing says where it is).
    """
    if scene.gripper is None:
        return []
    if not poses:
        _LOG.warning("the scene declares a gripper but no pose of it was given (/gripper/pose): "
                     "it is simulated without the gripper")
        return []
    g = scene.gripper
    times = np.array([(stamp - start_ns) * 1e-9 for stamp, _ in poses])
    positions = np.array([T[:3, 3] for _, T in poses])
    quaternions = Rotation.from_matrix(np.array([T[:3, :3] for _, T in poses])).as_quat()
    return [Collider(g.shape, g.size, times, positions, quaternions,
                     friction=Collider.friction if g.friction is None else g.friction, name="gripper")]


def effects_of(scene: Scene, objects: Sequence[ObjectModel]) -> list:
    """Gravity (declared or DEFAULT_GRAVITY) and the declared simulator effects, as declared."""
    names = [o.name for o in objects]
    effects = []
    declared = {e.name: e for e in scene.effects}
    gravity = declared.pop("gravity", None)
    effects.append(Gravity(g=tuple(gravity.params.get("g", DEFAULT_GRAVITY)) if gravity
                           else DEFAULT_GRAVITY))
    for name, effect in declared.items():
        if name in SENSOR_EFFECTS:
            continue
        if name not in BUILTIN_EFFECTS:
            raise ValueError(f"declared effect {name!r} is not a simulator effect "
                             f"(known: {', '.join(sorted(BUILTIN_EFFECTS))})")
        values = {key: _per_object(value, names) for key, value in effect.params.items()}
        effects.append(BUILTIN_EFFECTS[name](**values))
    return effects


def _per_object(value, names: Sequence[str]):
    if isinstance(value, Mapping):
        unknown = sorted(set(value) - set(names))
        if unknown:
            raise ValueError(f"effect parameter for unknown object(s) {unknown}")
        return [[float(value.get(n, 0.0)) for n in names]]
    return value
