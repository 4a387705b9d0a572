"""What-if requests to the twin: new initial velocities, swapped material parameters.

MOSIV's new interactions: the identified twin rolled out again from the first observed frame
with some objects' initial velocities or material parameters replaced, the rest as identified.
A request is two YAML texts by object name (prediction_node's parameters of the same names):

    initial_velocities: "{ball: [0.5, 0.0, 1.2]}"       # m/s; six values add rad/s
    swapped_params: "{clay: {yield_stress: 1500}}"       # SI; a friction angle as friction_angle_deg

Three velocity values replace an object's linear velocity and keep its identified spin; six
replace both.

What it is for: parsing a request and checking it against the objects it applies to.
What it is not for: the rollout (``twin.Twin.what_if``) or ROS (``nodes.prediction_node``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import yaml

from mosiv_ros.config import MAX_SPEED, MAX_SPIN
from mosiv_ros.io.errors import shown
from mosiv_ros.io.scene import load_yaml
from mosiv_ros.sim.materials import FAMILY_PARAMS, MATERIAL_PARAMS, in_sim_units

_SPECS = {spec.name: spec for spec in MATERIAL_PARAMS}


@dataclass(frozen=True)
class WhatIf:
    """New initial velocities (3 or 6 values) and swapped parameters (simulator units) by name."""

    velocities: dict[str, list[float]] = field(default_factory=dict)
    params: dict[str, dict[str, float]] = field(default_factory=dict)

    @classmethod
    def parse(cls, velocities: str = "", params: str = "") -> WhatIf:
        """A request from the two YAML texts (empty: none); ValueError saying what is wrong."""
        parsed_v = {name: _numbers(f"initial_velocities: {name}", value)
                    for name, value in _mapping("initial_velocities", velocities).items()}
        for name, values in parsed_v.items():
            if len(values) not in (3, 6):
                raise ValueError(f"initial_velocities: {name}: expected [vx, vy, vz] (m/s) or [vx, vy, "
                                 f"vz, wx, wy, wz] (m/s, rad/s), got {len(values)} values")
            for size, limit, unit in ((math.hypot(*values[:3]), MAX_SPEED, "m/s"),
                                      (math.hypot(*values[3:]), MAX_SPIN, "rad/s")):
                if size > limit:
                    raise ValueError(f"initial_velocities: {name}: {size:g} {unit} is above the "
                                     f"limit of {limit:g} {unit}")
        parsed_p = {}
        for name, values in _mapping("swapped_params", params).items():
            if not isinstance(values, dict) or not values:
                raise ValueError(f"swapped_params: {name}: expected a mapping {{parameter: value}}, "
                                 f"got {shown(values)}")
            given = {str(key): _numbers(f"swapped_params: {name}.{key}", [value])[0]
                     for key, value in values.items()}
            parsed_p[name] = in_sim_units(given)
        return cls(parsed_v, parsed_p)

    def __bool__(self) -> bool:
        return bool(self.velocities or self.params)

    def check(self, families: Mapping[str, str]) -> None:
        """ValueError unless every named object is in ``families`` (name: material family).

        Every swapped parameter must also be one its family uses, and in range.
        """
        for name in [*self.velocities, *self.params]:
            if name not in families:
                raise ValueError(f"what-if request names unknown object {shown(name)}; "
                                 f"objects: {', '.join(families)}")
        for name, values in self.params.items():
            family = families[name]
            for key, value in values.items():
                if key not in FAMILY_PARAMS[family]:
                    raise ValueError(f"swapped_params: {name} ({family}) has no parameter {shown(key)}; "
                                     f"its parameters: {', '.join(FAMILY_PARAMS[family])}")
                if not _SPECS[key].in_range(value):
                    raise _SPECS[key].out_of_range(value, f"object {shown(name)} ({family})")

    def velocity(self, identified: np.ndarray, names: Sequence[str]) -> np.ndarray:
        """The (K, 6) initial velocities: ``identified`` with the requested ones replaced."""
        velocity = np.array(identified, dtype=np.float64)
        for name, values in self.velocities.items():
            velocity[list(names).index(name), : len(values)] = values
        return velocity

    def describe(self) -> str:
        """One line for logs."""
        parts = [f"{name} v={values}" for name, values in self.velocities.items()]
        parts += [f"{name} {key}={value:g}" for name, values in self.params.items()
                  for key, value in values.items()]
        return "; ".join(parts)


def _mapping(what: str, text: str) -> dict:
    try:
        data = load_yaml(text) if text.strip() else {}
    except yaml.YAMLError as error:
        raise ValueError(f"{what}: not valid YAML ({error})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{what}: expected a mapping by object name, got {shown(text)}")
    return {str(name): value for name, value in data.items()}


def _numbers(what: str, values: object) -> list[float]:
    """Finite floats; numbers YAML 1.1 reads as text (``6.0e4``, ``1e5``) count as numbers."""
    try:
        if not isinstance(values, list) or any(isinstance(v, bool) for v in values):
            raise ValueError
        numbers = [float(v) for v in values]
    except (TypeError, ValueError):
        numbers = []
    if not numbers or not all(math.isfinite(v) for v in numbers):
        raise ValueError(f"{what}: expected finite numbers, got {shown(values)}")
    return numbers
