"""Reading one mapping of a YAML description field by field, naming the field in every error.

What it is for: the one way scene YAML is checked, by the bag's scene declaration's ground and
gripper (``io.scene``) and by the synthetic recorder's scene files (``synth.scene_file``,
``synth.effects``): typed getters with defaults and range checks, and a final check that no key
was left unread (a misspelt key must not vanish silently). Every problem is a ``SceneError``
whose ``field`` is the full path, e.g. ``objects[1].radius``.
What it is not for: what a scene means (the schemas are in ``io.scene`` and ``synth.scene_file``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mosiv_ros.io.errors import SceneError, shown

MISSING: Any = object()
"""Default of a required key."""


def is_number(value: object) -> bool:
    """True for int and float values (not bool), finite or not."""
    return isinstance(value, int | float) and not isinstance(value, bool)


class Fields:
    """One mapping at ``where`` (e.g. ``objects[0]``) and the keys read from it so far."""

    def __init__(self, raw: object, where: str) -> None:
        if not isinstance(raw, dict):
            raise SceneError(where, f"expected a mapping, got {shown(raw)}")
        self.raw = raw
        self.where = where
        self.asked: list[str] = []

    def path(self, key: str) -> str:
        """The full field name of ``key``."""
        return f"{self.where}.{key}" if self.where else key

    def has(self, key: str) -> bool:
        """Whether ``key`` is given (and counts it as read)."""
        if key not in self.asked:
            self.asked.append(key)
        return key in self.raw

    def get(self, key: str, default: Any = MISSING) -> Any:
        """The raw value of ``key``; ``default`` when absent, an error when required."""
        if self.has(key):
            return self.raw[key]
        if default is MISSING:
            raise SceneError(self.path(key), "missing")
        return default

    def number(
        self,
        key: str,
        default: Any = MISSING,
        *,
        positive: bool = False,
        lower: float | None = None,
        upper: float | None = None,
    ) -> float:
        """A finite number, optionally > 0 or within [lower, upper]."""
        value = self.get(key, default)
        return check_number(value, self.path(key), positive=positive, lower=lower, upper=upper)

    def integer(self, key: str, default: Any = MISSING, *, lower: int = 1) -> int:
        """An integer >= ``lower``."""
        value = self.get(key, default)
        if not isinstance(value, int) or isinstance(value, bool):
            raise SceneError(self.path(key), f"expected an integer, got {shown(value)}")
        if value < lower:
            raise SceneError(self.path(key), f"must be >= {lower}, got {value}")
        return value

    def vector(self, key: str, size: int, default: Any = MISSING, *, positive: bool = False) -> np.ndarray:
        """A list of ``size`` finite numbers, as a float64 array."""
        value = self.get(key, default)
        return check_vector(value, self.path(key), size, positive=positive)

    def string(self, key: str, default: Any = MISSING, choices: tuple[str, ...] | None = None) -> str:
        """A non-empty string, optionally one of ``choices``."""
        value = self.get(key, default)
        if not isinstance(value, str) or not value.strip():
            raise SceneError(self.path(key), f"expected a non-empty string, got {shown(value)}")
        if choices is not None and value not in choices:
            raise SceneError(self.path(key), f"unknown value {shown(value)} (expected one of {', '.join(choices)})")
        return value

    def boolean(self, key: str, default: Any = MISSING) -> bool:
        """True or false."""
        value = self.get(key, default)
        if not isinstance(value, bool):
            raise SceneError(self.path(key), f"expected true or false, got {shown(value)}")
        return value

    def section(self, key: str, default: Any = MISSING) -> Fields:
        """The mapping under ``key`` (``default``, e.g. ``{}``, when absent)."""
        return Fields(self.get(key, default), self.path(key))

    def items(self, key: str, default: Any = MISSING) -> list[tuple[str, object]]:
        """(field name, raw value) of each element of the list under ``key``."""
        value = self.get(key, default)
        if not isinstance(value, list):
            raise SceneError(self.path(key), f"expected a list, got {shown(value)}")
        return [(f"{self.path(key)}[{i}]", item) for i, item in enumerate(value)]

    def done(self, what: str = "") -> None:
        """Raise on the first key that no getter asked for, listing the allowed ones."""
        unknown = [key for key in self.raw if key not in self.asked]
        if unknown:
            allowed = ", ".join(self.asked)
            raise SceneError(self.path(str(unknown[0])), f"unknown key (allowed{what}: {allowed})")


def check_number(
    value: object,
    where: str,
    *,
    positive: bool = False,
    lower: float | None = None,
    upper: float | None = None,
) -> float:
    """``value`` as a float if it is a finite number meeting the bounds; SceneError otherwise."""
    if not is_number(value) or not math.isfinite(value):
        raise SceneError(where, f"expected a finite number, got {shown(value)}")
    if positive and not value > 0:
        raise SceneError(where, f"must be positive, got {value}")
    if (lower is not None and value < lower) or (upper is not None and value > upper):
        raise SceneError(where, f"{value} is outside [{lower:g}, {upper:g}]"
                         if lower is not None and upper is not None
                         else f"must be {'>=' if lower is not None else '<='} "
                              f"{lower if lower is not None else upper}, got {value}")
    return float(value)


def check_vector(value: object, where: str, size: int, *, positive: bool = False) -> np.ndarray:
    """``value`` as a float64 array if it is a list of ``size`` finite numbers."""
    if not isinstance(value, list | tuple) or len(value) != size:
        raise SceneError(where, f"expected a list of {size} numbers, got {shown(value)}")
    return np.array([check_number(v, f"{where}[{i}]", positive=positive) for i, v in enumerate(value)])
