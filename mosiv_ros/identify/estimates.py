"""Identified parameters with their uncertainty, per object: what identify_node publishes.

Uncertainty (Laplace approximation): the loss curvature H_j along each free coordinate u_j comes
from the second difference (L(u + h e_j) - 2 L(u) + L(u - h e_j)) / h^2 of forward rollouts, all
2P + 1 of them in one batched rollout. The fit is treated as M = frames x objects independent
observations whose residual variance is the fitted loss, so the negative log-likelihood is
M L(u) / (2 L_min) and var(u_j) = 2 L_min / (M H_j); the delta method carries the standard
deviation to the parameter's own units. Correlations between parameters are ignored (diagonal
Hessian), which can make a standard deviation optimistic when two parameters trade off.

Status per object, and for the scene's own parameters (ground, effects), as in diagnostic_msgs
(``OK``, ``WARN``, ``ERROR``): WARN when one of its parameters is poorly identified (the
curvature is not positive, so the data do not pin it down, or the standard deviation exceeds a
factor of 2 for scale parameters or a quarter of the range for bounded ones) or ended on a bound
of the fit (a modulus at ``max_modulus``: the data show only that the object is at least that
stiff); ERROR when the fit failed.

The estimates file (``Estimates.write``, identify_node's ``output_yaml``) is a ROS 2 parameter
file: its one parameter ``estimates`` carries the estimates document (YAML text) for any node,
so that ``ros2 run mosiv_ros prediction_node --ros-args --params-file FILE`` predicts from it.

What it is for: turning a ``FitResult`` into estimates, YAML and key-value pairs.
What it is not for: the fit itself (``identify.fit``) or ROS messages (``nodes``).
"""

from __future__ import annotations

import logging
import math
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from mosiv_ros.identify.coordinates import Coordinate
from mosiv_ros.identify.fit import FitResult, Identifier
from mosiv_ros.io.files import write_text
from mosiv_ros.io.scene import load_yaml
from mosiv_ros.sim.materials import FAMILY_PARAMS

_LOG = logging.getLogger(__name__)

OK, WARN, ERROR = "OK", "WARN", "ERROR"
LEVELS = (OK, WARN, ERROR)
"""Index = diagnostic_msgs/DiagnosticStatus level (OK 0, WARN 1, ERROR 2)."""
VELOCITY_KEYS = ("vx", "vy", "vz", "wx", "wy", "wz")
FAMILY_SCORE_PREFIX = "family_score."
"""Status key of a candidate family's held-out error: ``family_score.<family>`` (m)."""
SCENE_STATUS = "mosiv/scene"
FORMAT = "mosiv.estimates/1"
"""``format`` of the estimates document."""
PARAMETER = "estimates"
"""The ROS parameter that carries the estimates document in an estimates file (prediction_node's)."""
ESTIMATES_FILE = "estimates.yaml"
"""The estimates file's name in an output directory (``mosiv run``, ``close-loop``, ``graph``)."""

Status = tuple[str, str, str, str, list[tuple[str, str]]]
"""(name, hardware_id, level, message, key-value pairs): a DiagnosticStatus as plain data."""
CURVATURE_STEP = 0.1
"""Step h in optimisation coordinates for the curvature (10 % for scale parameters)."""
SCALE_FACTOR_LIMIT = math.log(2.0)
BOUNDED_FRACTION_LIMIT = 0.25


@dataclass
class ObjectEstimate:
    """One object's identified parameters (SI units) and standard deviations."""

    id: int
    name: str
    family: str
    params: dict[str, float]
    std: dict[str, float] = field(default_factory=dict)
    loss: float = float("nan")
    level: str = OK
    message: str = ""
    velocity: list[float] = field(default_factory=lambda: [0.0] * 6)
    """Initial linear (m/s) and angular (rad/s) velocity at the first observed frame."""
    family_scores: dict[str, float] = field(default_factory=dict)
    """When the family was chosen (``identify.family``): each candidate family's held-out error,
    a mean Chamfer distance in m (inf: its fit failed). Empty for a declared family."""

    def key_values(self) -> list[tuple[str, str]]:
        """The DiagnosticStatus ``values`` of this object.

        family, the candidate families' held-out errors (``family_score.<family>``, m) when it
        was chosen, each parameter (SI), ``<name>_std``, the loss, and the initial velocity (vx ..
        wz, m/s and rad/s).
        """
        pairs = [("family", self.family)]
        pairs += [(FAMILY_SCORE_PREFIX + f, f"{v:.6g}") for f, v in self.family_scores.items()]
        for name, value in self.params.items():
            pairs.append((name, f"{value:.9g}"))
            if name in self.std:
                pairs.append((f"{name}_std", f"{self.std[name]:.6g}"))
        pairs.append(("loss", f"{self.loss:.6g}"))
        pairs += [(key, f"{v:.9g}") for key, v in zip(VELOCITY_KEYS, self.velocity, strict=True)]
        return pairs


@dataclass
class Estimates:
    """Every object's estimate, the fitted scene parameters (ground, effects) and the set-up."""

    objects: list[ObjectEstimate]
    scene: dict[str, float] = field(default_factory=dict)
    scene_std: dict[str, float] = field(default_factory=dict)
    stamp_ns: int = 0
    frames: int = 0
    frame_dt: float = 0.0
    scene_level: str = OK
    scene_message: str = ""

    def to_yaml(self) -> str:
        """The estimates document (YAML text): what the ``estimates`` parameter carries."""
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    @classmethod
    def from_yaml(cls, text: str) -> Estimates:
        """Estimates from the document ``to_yaml`` gives (ValueError if it is not one)."""
        try:
            data = load_yaml(text)
        except yaml.YAMLError as error:
            raise ValueError(f"estimates are not valid YAML ({error})") from None
        if not isinstance(data, dict):
            raise ValueError(f"not a mosiv estimates document (a {type(data).__name__})")
        try:
            return cls.from_dict(data)
        except (KeyError, TypeError, AttributeError) as error:
            raise ValueError(f"malformed estimates document (at {error})") from None

    def to_dict(self) -> dict:
        return {
            "format": FORMAT, "stamp_ns": self.stamp_ns, "frames": self.frames,
            "frame_dt": self.frame_dt,
            "objects": [{"id": o.id, "name": o.name, "family": o.family, "params": o.params,
                         "std": o.std, "loss": o.loss, "level": o.level, "message": o.message,
                         "velocity": o.velocity,
                         **({"family_scores": o.family_scores} if o.family_scores else {})}
                        for o in self.objects],
            "scene": self.scene, "scene_std": self.scene_std, "scene_level": self.scene_level,
            "scene_message": self.scene_message,
        }

    @classmethod
    def from_dict(cls, data: dict) -> Estimates:
        if data.get("format") != FORMAT:
            raise ValueError(f"not a mosiv estimates document (format {data.get('format')!r})")
        objects = [ObjectEstimate(int(o["id"]), o["name"], o["family"],
                                  {k: float(v) for k, v in o["params"].items()},
                                  {k: float(v) for k, v in o.get("std", {}).items()},
                                  float(o.get("loss", "nan")), o.get("level", OK),
                                  o.get("message", ""),
                                  [float(v) for v in o.get("velocity", [0.0] * 6)],
                                  {k: float(v) for k, v in o.get("family_scores", {}).items()})
                   for o in data["objects"]]
        return cls(objects, {k: float(v) for k, v in data.get("scene", {}).items()},
                   {k: float(v) for k, v in data.get("scene_std", {}).items()},
                   int(data.get("stamp_ns", 0)), int(data.get("frames", 0)),
                   float(data.get("frame_dt", 0.0)), data.get("scene_level", OK),
                   data.get("scene_message", ""))

    def statuses(self) -> list[Status]:
        """One status per object (``mosiv/<name>``, hardware_id = its id) and one for the scene."""
        out = [(f"mosiv/{o.name}", str(o.id), o.level, o.message, o.key_values())
               for o in self.objects]
        pairs = [(k, f"{v:.9g}") for k, v in self.scene.items()]
        pairs += [(f"{k}_std", f"{v:.6g}") for k, v in self.scene_std.items()]
        pairs += [("stamp_ns", str(self.stamp_ns)), ("frames", str(self.frames)),
                  ("frame_dt", f"{self.frame_dt:.9g}")]
        out.append((SCENE_STATUS, "", self.scene_level, self.scene_message, pairs))
        return out

    @classmethod
    def from_statuses(cls, statuses: list[Status]) -> Estimates:
        """Estimates back from ``statuses()`` (ValueError naming the status if one is malformed)."""
        objects, scene, scene_std = [], {}, {}
        meta: dict[str, str] = {}
        level, message = OK, ""
        for name, hardware_id, status_level, status_message, pairs in statuses:
            values = dict(pairs)
            try:
                if name == SCENE_STATUS:
                    level, message = status_level, status_message
                    for key, value in values.items():
                        if key in ("stamp_ns", "frames", "frame_dt"):
                            meta[key] = value
                        elif key.endswith("_std"):
                            scene_std[key[:-4]] = float(value)
                        else:
                            scene[key] = float(value)
                    continue
                if not name.startswith("mosiv/"):
                    continue
                family = values.pop("family")
                scores = {k[len(FAMILY_SCORE_PREFIX):]: float(values.pop(k)) for k in list(values)
                          if k.startswith(FAMILY_SCORE_PREFIX)}
                loss = float(values.pop("loss", "nan"))
                velocity = [float(values.pop(k, 0.0)) for k in VELOCITY_KEYS]
                std = {k[:-4]: float(values.pop(k)) for k in list(values) if k.endswith("_std")}
                params = {k: float(v) for k, v in values.items()}
                objects.append(ObjectEstimate(int(hardware_id), name[len("mosiv/"):], family, params,
                                              std, loss, status_level, status_message, velocity,
                                              scores))
            except (KeyError, ValueError) as error:
                raise ValueError(f"status {name!r}: malformed estimate ({error})") from None
        return cls(objects, scene, scene_std, int(meta.get("stamp_ns", 0)),
                   int(meta.get("frames", 0)), float(meta.get("frame_dt", 0.0)), level, message)

    def file_text(self, name: str) -> str:
        """The estimates file named ``name``: a ROS 2 parameter file whose ``estimates`` is the document."""
        return (f"# mosiv_ros material estimates ({FORMAT}), as a ROS 2 parameter file:\n"
                f"#   ros2 run mosiv_ros prediction_node --ros-args --params-file {name}\n"
                f"/**:\n  ros__parameters:\n    {PARAMETER}: |\n"
                + textwrap.indent(self.to_yaml(), " " * 6))

    def write(self, path: str | Path) -> Path:
        """Write the estimates file (``file_text``) whole, or leave the one there as it was."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        return write_text(path, self.file_text(path.name))

    @classmethod
    def read(cls, path: str | Path) -> Estimates:
        """Estimates from a file ``write`` wrote (ValueError naming the file if it is not one)."""
        path = Path(path)
        try:
            data = load_yaml(path.read_text(encoding="utf-8"))
            text = data["/**"]["ros__parameters"][PARAMETER]
        except (yaml.YAMLError, TypeError, KeyError):
            raise ValueError(f"{path}: not a mosiv estimates file (a ROS 2 parameter file whose "
                             f"'/**' node carries the parameter {PARAMETER!r})") from None
        try:
            return cls.from_yaml(text)
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None


def coordinate_std(identifier: Identifier, result: FitResult,
                   frames: int | None = None) -> np.ndarray:
    """Standard deviation of each free coordinate u_j (inf where the curvature is not positive)."""
    u, h = result.u, CURVATURE_STEP
    candidates = [u]
    for j in range(len(u)):
        for sign in (1.0, -1.0):
            shifted = u.copy()
            shifted[j] += sign * h
            candidates.append(shifted)
    # one batch, one time step, on every device: the shifts are too small to change the stable
    # step much, and a loss differs by up to 10 % between time steps, more than a shift changes it
    losses = identifier.search.batch_losses(np.array(candidates), result.velocity, frames, together=True)
    base = losses[0]
    obs = identifier.problem.observations
    last = min(frames or obs.n_frames - 1, obs.n_frames - 1)
    # a term per object and observed frame (a frame the stream lost has no points and no term)
    n_terms = max(1, sum(any(len(p) for p in frame) for frame in obs.points[1:last + 1])) * obs.n_objects
    std = np.full(len(u), np.inf)
    for j in range(len(u)):
        curvature = (losses[1 + 2 * j] - 2 * base + losses[2 + 2 * j]) / h**2
        if np.isfinite(curvature) and curvature > 0 and np.isfinite(base):
            std[j] = math.sqrt(2 * max(base, 1e-30) / (n_terms * curvature))
    return std


def estimates_of(identifier: Identifier, result: FitResult, std_u: np.ndarray | None = None,
                 failed: dict[str, str] | None = None) -> Estimates:
    """Per-object estimates (with standard deviations when ``std_u`` is given)."""
    problem = identifier.problem
    failed = failed or {}
    objects = []
    scene, scene_std, scene_poor = {}, {}, []
    per_object: dict[str, dict[str, tuple[float, float, bool, str]]] = {o.name: {} for o in problem.objects}
    for j, entry in enumerate(result.entries):
        theta = float(entry.coordinate.to_theta(result.u[j]))
        sigma_u = float(std_u[j]) if std_u is not None else float("nan")
        sigma = sigma_u * float(entry.coordinate.dtheta_du(result.u[j]))
        bound = f" (at the fit's bound {theta:.3g})" if entry.coordinate.at_bound(theta) else ""
        poor = bool(bound) or _poorly_identified(entry.coordinate, sigma_u, sigma)
        if entry.per_object:
            per_object[problem.objects[entry.index[1]].name][entry.name] = (theta, sigma, poor, bound)
        else:
            scene[entry.label] = theta
            scene_std[entry.label] = sigma
            if poor:
                scene_poor.append(entry.label + bound)
    for k, obj in enumerate(problem.objects):
        params = {name: float(identifier.sim.params.get(name)[0, k])
                  for name in FAMILY_PARAMS[obj.family]}
        std, poor = {}, []
        for name, (theta, sigma, bad, bound) in per_object[obj.name].items():
            params[name] = theta
            std[name] = sigma
            if bad:
                poor.append(name + bound)
        level, message = OK, "fitted"
        if obj.name in failed:
            level, message = ERROR, failed[obj.name]
        elif poor:
            level, message = WARN, f"poorly identified: {', '.join(poor)}"
        objects.append(ObjectEstimate(obj.id, obj.name, obj.family, params, std,
                                      float(result.per_object_loss[k]), level, message,
                                      [float(v) for v in result.velocity[k]]))
    obs = problem.observations
    scene_level, scene_message = (WARN, f"poorly identified: {', '.join(scene_poor)}") if scene_poor else (OK, "fitted")
    return Estimates(objects, scene, scene_std, obs.start_ns, obs.n_frames, obs.frame_dt,
                     scene_level, scene_message)


def _poorly_identified(coordinate: Coordinate, sigma_u: float, sigma: float) -> bool:
    if math.isnan(sigma_u):
        return False  # no uncertainty computed
    if not math.isfinite(sigma_u):
        return True
    if coordinate.kind == "log":
        return sigma_u > SCALE_FACTOR_LIMIT
    if coordinate.kind == "logit":
        return sigma > BOUNDED_FRACTION_LIMIT * (coordinate.upper - coordinate.lower)
    return False
