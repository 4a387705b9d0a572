"""Effects the synthetic recorder puts into a recording, each declared or undeclared.

What it is for: the catalogue of effect types a scene file may list (``EFFECT_TYPES``), their
parameters and checks, and what each one becomes: simulator effects and ground parameters, a
camera's time offset, mask noise, the bag's scene declaration (declared effects only) and the
ground-truth entry (every effect). An undeclared effect acts on the data exactly as a declared
one; it only never reaches the bag.
What it is not for: the physics (``mosiv_ros.sim.effects``) or the rendering (``render``).

Types and parameters (SI units; a per-object value is a number for every object or a mapping
from object name to number, objects left out getting the simulator's default):

- ``gravity`` {g: [gx, gy, gz]}: a different (e.g. tilted) gravity vector, m/s^2.
- ``wind`` {a: [ax, ay, az]}: a uniform body acceleration, m/s^2 (``BodyForce``).
- ``drag`` {coefficient}: quadratic air drag a = -c |v| v, 1/m per object (``QuadraticDrag``).
- ``linear_drag`` {coefficient}: a = -c v, 1/s per object (``LinearDrag``).
- ``damping`` {viscosity}: Kelvin-Voigt velocity damping, Pa*s per object.
- ``periodic_field`` {a: [ax, ay, az], wavelength}: a position-dependent body force
  a sin(2 pi x / wavelength), m/s^2 and m (``PeriodicField``; outside the loop closure's library).
- ``floor_tilt`` {normal: [nx, ny, nz]}: the floor plane's normal (it still passes through the
  ground height along that normal); the rendered floor tilts with it.
- ``floor_friction`` {friction}: the floor's Coulomb coefficient instead of the nominal one
  (``sim.boundaries.GROUND_FRICTION``).
- ``camera_time_offset`` {camera, offset}: that camera shows the scene at t + offset (s) while
  its frames are stamped t (a badly synchronised camera).
- ``mask_noise`` {boundary, speckle}: each object-boundary pixel takes the label of a random
  4-neighbour with probability ``boundary``; any pixel takes a uniformly random label 0..K with
  probability ``speckle``.

Declaration (DESIGN.md): a declared simulator effect, time offset or mask noise is a
``DeclaredEffect`` named after its type; a declared ``floor_tilt`` / ``floor_friction`` is the
declared ground's ``normal`` / ``friction``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mosiv_ros.io.errors import SceneError, shown
from mosiv_ros.io.fields import Fields, check_number
from mosiv_ros.io.scene import DeclaredEffect, DeclaredGround
from mosiv_ros.sim import BUILTIN_EFFECTS, Effect, Gravity, Ground
from mosiv_ros.sim.boundaries import GROUND_PARAMS
from mosiv_ros.sim.params import ParamSpec

FLOOR_EFFECTS = ("floor_tilt", "floor_friction")
RECORDER_EFFECTS = ("camera_time_offset", "mask_noise")
EFFECT_TYPES = (*BUILTIN_EFFECTS, *FLOOR_EFFECTS, *RECORDER_EFFECTS)
NOMINAL_GROUND = Ground()
"""The floor every consumer assumes unless told otherwise: normal +z, the nominal friction."""


@dataclass
class EffectSpec:
    """One effect of a scene: its type, whether the bag declares it, its parameters (SI).

    Per-object parameters hold a value for every object, by name; vectors are lists.
    """

    type: str
    declared: bool
    params: dict[str, Any]

    def ground_truth(self) -> dict[str, Any]:
        """The effect's entry in ground_truth.yaml."""
        return {"type": self.type, "declared": self.declared, "params": self.params}


def parse_effect(raw: object, where: str, objects: list[str], cameras: list[str]) -> EffectSpec:
    """Check one ``effects[i]`` entry of a scene file against the objects and cameras."""
    fields = Fields(raw, where)
    kind = fields.string("type", choices=EFFECT_TYPES)
    declared = fields.boolean("declared")
    params: dict[str, Any] = {}
    if kind in BUILTIN_EFFECTS:
        for spec in BUILTIN_EFFECTS[kind].params:
            params[spec.name] = _sim_value(fields, spec, objects)
    elif kind == "floor_tilt":
        normal = fields.vector("normal", 3)
        if not np.any(normal) or normal[2] <= 0:
            raise SceneError(fields.path("normal"), f"must point upwards (z > 0), got {normal.tolist()}")
        params["normal"] = (normal / np.linalg.norm(normal)).tolist()
    elif kind == "floor_friction":
        spec = next(s for s in GROUND_PARAMS if s.name == "ground.friction")
        params["friction"] = fields.number("friction", lower=spec.lower, upper=spec.upper)
    elif kind == "camera_time_offset":
        params["camera"] = fields.string("camera", choices=tuple(cameras))
        params["offset"] = fields.number("offset")
        if params["offset"] == 0:
            raise SceneError(fields.path("offset"), "must not be 0 (that is no effect)")
    else:  # mask_noise
        params["boundary"] = fields.number("boundary", 0.0, lower=0.0, upper=1.0)
        params["speckle"] = fields.number("speckle", 0.0, lower=0.0, upper=1.0)
        if params["boundary"] == params["speckle"] == 0:
            raise SceneError(where, "mask_noise needs boundary or speckle > 0")
    fields.done(f" for {kind}")
    return EffectSpec(kind, declared, params)


def _sim_value(fields: Fields, spec: ParamSpec, objects: list[str]) -> Any:
    where = fields.path(spec.name)
    if spec.size == 3:
        vector = fields.vector(spec.name, 3)
        for i, value in enumerate(vector):
            check_number(value, f"{where}[{i}]", lower=spec.lower, upper=spec.upper)
        return vector.tolist()
    if not spec.per_object:
        return fields.number(spec.name, lower=spec.lower, upper=spec.upper)
    value = fields.get(spec.name)
    if not isinstance(value, dict):
        value = dict.fromkeys(objects, check_number(value, where, lower=spec.lower, upper=spec.upper))
    values = {name: float(spec.default) for name in objects}
    for name, v in value.items():
        if name not in objects:
            raise SceneError(f"{where}.{name}", f"unknown object (objects: {', '.join(objects)})")
        values[name] = check_number(v, f"{where}.{name}", lower=spec.lower, upper=spec.upper)
    return values


def check_unique(effects: list[EffectSpec]) -> None:
    """One effect per type: two of a kind would be ambiguous to declare and to apply."""
    seen: dict[str, int] = {}
    for index, effect in enumerate(effects):
        if effect.type in seen:
            raise SceneError(f"effects[{index}].type",
                             f"{shown(effect.type)} already given by effects[{seen[effect.type]}]")
        seen[effect.type] = index


def _of_type(effects: list[EffectSpec], kind: str) -> EffectSpec | None:
    return next((e for e in effects if e.type == kind), None)


def simulator_effects(effects: list[EffectSpec]) -> list[Effect]:
    """The simulator's effects: gravity (nominal unless overridden) and every other sim effect."""
    gravity = _of_type(effects, "gravity")
    result: list[Effect] = [Gravity(**gravity.params) if gravity else Gravity()]
    for effect in effects:
        if effect.type in BUILTIN_EFFECTS and effect.type != "gravity":
            result.append(BUILTIN_EFFECTS[effect.type](**effect.params))
    return result


def simulator_ground(effects: list[EffectSpec], height: float) -> Ground:
    """The simulated floor at ``height``, tilted and with the friction the floor effects say."""
    tilt, friction = _of_type(effects, "floor_tilt"), _of_type(effects, "floor_friction")
    return Ground(
        height=height,
        normal=tuple(tilt.params["normal"]) if tilt else NOMINAL_GROUND.normal,
        friction=friction.params["friction"] if friction else NOMINAL_GROUND.friction,
    )


def camera_offsets(effects: list[EffectSpec]) -> dict[str, float]:
    """Time offset (s) of each camera that has one."""
    offset = _of_type(effects, "camera_time_offset")
    return {offset.params["camera"]: offset.params["offset"]} if offset else {}


def declaration(effects: list[EffectSpec], ground_height: float) -> tuple[DeclaredGround, list[DeclaredEffect]]:
    """(declared ground, declared effects) for the bag's scene declaration.

    The ground always declares its height (the floor is in plain view); its normal and friction
    only when a declared floor effect sets them. Undeclared effects leave no trace here.
    """
    ground: dict[str, Any] = {"height": ground_height}
    declared = []
    for effect in effects:
        if not effect.declared:
            continue
        if effect.type == "floor_tilt":
            ground["normal"] = list(effect.params["normal"])
        elif effect.type == "floor_friction":
            ground["friction"] = effect.params["friction"]
        elif effect.type == "camera_time_offset":
            declared.append(DeclaredEffect(effect.type, {"offset": {effect.params["camera"]: effect.params["offset"]}}))
        else:
            declared.append(DeclaredEffect(effect.type, dict(effect.params)))
    return DeclaredGround(**ground), declared


def add_mask_noise(mask: np.ndarray, effects: list[EffectSpec], n_objects: int,
                   rng: np.random.Generator) -> np.ndarray:
    """``mask`` with the scene's mask noise applied (unchanged without a mask_noise effect)."""
    noise = _of_type(effects, "mask_noise")
    if noise is None:
        return mask
    padded = np.pad(mask, 1, mode="edge")
    neighbours = np.stack([padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]])
    on_boundary = np.any(neighbours != mask, axis=0)
    pick = rng.integers(0, 4, size=mask.shape)
    flip = on_boundary & (rng.random(mask.shape) < noise.params["boundary"])
    noisy = mask.copy()
    noisy[flip] = np.take_along_axis(neighbours, pick[None], axis=0)[0][flip]
    speckle = rng.random(mask.shape) < noise.params["speckle"]
    noisy[speckle] = rng.integers(0, n_objects + 1, size=int(speckle.sum()))
    return noisy
