"""Differentiable multi-object MLS-MPM simulation in Warp (CUDA or CPU); no ROS here.

``Simulator`` (``simulator``) runs a scene of objects (``materials``: elastic, plastic, sand,
fluid, with per-object parameters), boundaries (``boundaries``: ground, walls, kinematic
colliders) and effects (``effects``: the extension point for gravity, wind, drag, damping, ...),
for B parameter sets at once, and returns gradients of a loss on particle positions with respect
to every parameter, the initial velocities and the particle volumes.
"""

from mosiv_ros.sim.boundaries import Collider, Ground
from mosiv_ros.sim.effects import (
    BUILTIN_EFFECTS,
    BodyForce,
    Effect,
    Gravity,
    KelvinVoigtDamping,
    LinearDrag,
    QuadraticDrag,
)
from mosiv_ros.sim.errors import ParameterError, SimulationDiverged, SimulationError
from mosiv_ros.sim.materials import FAMILY_PARAMS, MATERIAL_PARAMS
from mosiv_ros.sim.params import ParamSpec
from mosiv_ros.sim.runtime import resolve_device
from mosiv_ros.sim.simulator import (
    WALL_RETRIES,
    Gradients,
    ObjectModel,
    Particles,
    QueuedRollout,
    SimConfig,
    SimState,
    Simulator,
    domain_around,
    reaches_walls,
)

__all__ = [
    "BUILTIN_EFFECTS", "BodyForce", "Collider", "Effect", "FAMILY_PARAMS", "Gradients", "Gravity",
    "Ground", "KelvinVoigtDamping", "LinearDrag", "MATERIAL_PARAMS", "ObjectModel", "ParamSpec",
    "ParameterError", "Particles", "QuadraticDrag", "QueuedRollout", "SimConfig", "SimulationDiverged",
    "SimulationError", "SimState", "Simulator", "WALL_RETRIES", "domain_around", "reaches_walls",
    "resolve_device",
]
