"""Well-conditioned optimisation coordinates for simulation parameters.

The optimiser moves an unconstrained coordinate u; the simulator sees theta(u), always inside
the parameter's valid range:

- scale parameters (a positive range spanning more than three decades, e.g. E, yield stress,
  or a range [0, >= 100] such as viscosity and drag): theta = exp(u) - offset, so that a step
  in u is a relative change of theta (offset 0, or 1e-9 of the range where 0 is allowed);
- bounded parameters (nu, friction angle, friction coefficients): theta = lower + (upper - lower)
  * sigmoid(u);
- anything else (gravity components, ground height): theta = u.

What it is for: mapping values, gradients and standard deviations between theta and u.
What it is not for: choosing which parameters to fit (``mosiv_ros.identify.fit``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mosiv_ros.sim.params import ParamSpec

_DECADES_FOR_LOG = 3.0
_ZERO_BOUNDED_SCALE = 100.0  # a range [0, >= 100] is a scale (viscosity, drag), not a fraction


@dataclass(frozen=True)
class Coordinate:
    """The map between a parameter's value theta and its optimisation coordinate u."""

    kind: str  # "log", "logit" or "linear"
    lower: float
    upper: float
    offset: float = 0.0  # log kind: theta = exp(u) - offset

    @classmethod
    def for_spec(cls, spec: ParamSpec) -> Coordinate:
        lower, upper = float(spec.lower), float(spec.upper)
        if lower > 0.0 and np.log10(upper / lower) > _DECADES_FOR_LOG:
            return cls("log", lower, upper)
        if lower == 0.0 and upper >= _ZERO_BOUNDED_SCALE:
            return cls("log", lower, upper, offset=upper * 1e-9)
        if np.isfinite(lower) and np.isfinite(upper) and upper - lower <= 10.0:
            return cls("logit", lower, upper)
        return cls("linear", lower, upper)

    def to_u(self, theta: np.ndarray) -> np.ndarray:
        theta = np.clip(np.asarray(theta, dtype=np.float64), self.lower, self.upper)
        if self.kind == "log":
            return np.log(theta + self.offset)
        if self.kind == "logit":
            s = np.clip((theta - self.lower) / (self.upper - self.lower), 1e-6, 1 - 1e-6)
            return np.log(s / (1 - s))
        return theta

    def to_theta(self, u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, dtype=np.float64)
        if self.kind == "log":
            return np.clip(np.exp(u) - self.offset, self.lower, self.upper)
        if self.kind == "logit":
            # strictly inside: float32 storage must not round onto or past a bound
            s = np.clip(1 / (1 + np.exp(-u)), 1e-6, 1 - 1e-6)
            return self.lower + (self.upper - self.lower) * s
        return np.clip(u, self.lower, self.upper)

    def clip_u(self, u: float) -> float:
        """The coordinate moved inside the range whose theta is in [lower, upper] (a logit's: all of R)."""
        if self.kind == "log":
            return float(np.clip(u, np.log(self.lower + self.offset), np.log(self.upper + self.offset)))
        if self.kind == "linear":
            return float(np.clip(u, self.lower, self.upper))
        return float(u)

    def at_bound(self, theta: float) -> bool:
        """Whether theta sits on a bound: the fit was held there, the data may want it further."""
        if self.kind == "logit":
            return False  # a sigmoid never reaches its bounds
        tolerance = 1e-9 * max(abs(theta), 1e-12)
        return bool(theta <= self.lower + tolerance or theta >= self.upper - tolerance)

    def dtheta_du(self, u: np.ndarray) -> np.ndarray:
        """Derivative of theta(u): chains a value gradient into u and a u-std into theta."""
        u = np.asarray(u, dtype=np.float64)
        if self.kind == "log":
            return np.exp(u)
        if self.kind == "logit":
            s = 1 / (1 + np.exp(-u))
            return (self.upper - self.lower) * s * (1 - s)
        return np.ones_like(u)
