"""The loop closure's effect library: effects a model may lack, each with its signature and knobs.

A ``Candidate`` is one effect the loop can add to a scene's model. It declares

- ``knobs(ctx)``: the parameters it adds (``Knob``: a label, the value the current model has,
  the step by which the signature is measured, the range);
- ``declare(scene, values, ctx)``: the scene declaration with the effect at those values. The
  simulator builds its effects and floor from the declaration (``mosiv_ros.simulation``, for
  the fit and the twin alike), so a candidate is only ever a change of declaration;
- ``free(ctx)``: the simulator parameters a refit fits (and, per object, those it keeps fixed);
- ``read(estimates, prediction, ctx)``: the fitted knob values from a refit's estimates (and,
  for an effect fitted on the observation side, from its rolled-out twin);
- ``reobserve(values, ctx)``: how the observations (stages 1-2) change at those values, as
  arguments of ``Reobserver.observe`` ({} where they stay as they are): a sensor effect's
  correction, or the floor that bounds the carving for a tilted floor;
- ``force_law(ctx)``: the external force per unit mass its knobs put on an object in free flight
  (``loop.freeflight.ForceLaw``), or None for an effect that puts none there (a floor's, an
  internal damping, a sensor's): the evidence no material can absorb (``loop.freeflight``).

Its residual signature is what the effect does to the residual: the loop switches each knob on
by its ``probe`` step alone, in the current twin for a physical effect (rolled out; a tilted
floor too, whose remade observations follow it into the refit) or in the observations for a
sensor effect (``sensor``), and takes the change of the residual features (centroid
paths, shape) per unit of the knob. The effect explains the
residual to the degree that a combination of those columns, with the knobs inside their ranges,
reproduces it (``closure``). Adding an effect means adding a ``Candidate`` here (and, for a new
physical term, an ``Effect`` in ``mosiv_ros.sim.effects``); nothing else changes. A sensor
effect's ``declare`` adds a declaration the simulator ignores (``mosiv_ros.simulation``'s
``SENSOR_EFFECTS``); its ``reobserve`` does the work.

The library (``LIBRARY``):

- ``drag``: quadratic air drag a = -c |v| v per moving object (1/m): a deceleration growing with
  the square of the speed, strongest in fast flight;
- ``linear_drag``: a = -c v per moving object (1/s): a deceleration proportional to speed;
- ``wind``: a uniform horizontal acceleration (m/s^2), in flight and while sliding. A gravity
  tilted against the declared vertical acts the same way on everything the cameras see (its
  horizontal part is a uniform acceleration, its vertical change is second order), so this
  candidate stands for both;
- ``floor_tilt``: the floor's normal tilted by (nx, ny) (the normal is (nx, ny, 1) normalised):
  a downhill acceleration only where an object touches the floor. With the recording at hand
  its refit fits observations remade with the tilted floor as their lower bound (rounded to
  ``QUANTUM``): the declared floor cuts away what lies below it, which on a floor that falls
  away is the bottom of the objects;
- ``floor_friction``: the declared floor friction is wrong: a deceleration along the sliding
  direction while on the floor (only when the declaration gives the friction; otherwise it is
  fitted anyway);
- ``damping``: Kelvin-Voigt velocity damping per moving object (Pa*s): deformation (bounces,
  wobble) dies out faster; it shows in the shape and in the rebound, not in free flight;
- ``camera_time_offset``: a sensor effect, one offset per camera (s, relative to the median
  camera): a camera's frames show the scene at t + offset under stamp t, so its silhouettes
  lead or lag the others' and the carved volume shrinks and shifts along the motion. Tried
  only with the recording at hand and at least three cameras.

What it is not for: the loop itself (``closure``) or the physics (``mosiv_ros.sim``).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from mosiv_ros.identify.estimates import Estimates
from mosiv_ros.identify.observations import View
from mosiv_ros.io.scene import DeclaredEffect, Scene
from mosiv_ros.loop.freeflight import FIELD_BOUND, ForceLaw, field_law
from mosiv_ros.loop.observations import Observations, Reobserver
from mosiv_ros.loop.residual import camera_time_offset
from mosiv_ros.predict.twin import Prediction
from mosiv_ros.sim.effects import FIELD_FEATURES


@dataclass
class Context:
    """What a candidate needs to know of the model and the data.

    Object names, which move, the scene; the frame period, the cameras, the observations the
    loop was given and, when the recording is at hand, a ``Reobserver`` to remake them; the
    device silhouettes render on (the fit's).
    """

    names: list[str]
    moving: list[bool]
    scene: Scene
    frame_dt: float
    views: list[View]
    given: Observations
    reobserver: Reobserver | None = None
    device: str = "cpu"

    @property
    def moving_names(self) -> list[str]:
        return [n for n, m in zip(self.names, self.moving, strict=True) if m]

    @property
    def static_names(self) -> list[str]:
        return [n for n, m in zip(self.names, self.moving, strict=True) if not m]


@dataclass
class Knob:
    """One parameter a candidate adds.

    ``label``, its value in the current model (``neutral``), the step that measures its
    signature (``probe``) and its valid range.
    """

    label: str
    neutral: float
    probe: float
    lower: float
    upper: float


class Candidate:
    """Base class of the library's effects (see the module docstring)."""

    name: ClassVar[str] = ""
    doc: ClassVar[str] = ""
    signature: ClassVar[str] = ""
    """The residual it predicts, in words (for the report)."""
    sensor: ClassVar[bool] = False
    """It changes the observations only: its signature is measured on them, the twin unchanged."""

    def applicable(self, ctx: Context) -> bool:
        return not any(e.name == self.name for e in ctx.scene.effects)

    def knobs(self, ctx: Context) -> list[Knob]:
        raise NotImplementedError

    def declare(self, scene: Scene, values: dict[str, float], ctx: Context) -> Scene:
        raise NotImplementedError

    def free(self, ctx: Context) -> tuple[list[str], dict[str, set[str]]]:
        raise NotImplementedError

    def read(self, estimates: Estimates, prediction: Prediction, ctx: Context) -> dict[str, float]:
        raise NotImplementedError

    def reobserve(self, values: dict[str, float], ctx: Context) -> dict[str, object]:
        """``Reobserver.observe`` arguments of the observations at ``values``; {}: unchanged."""
        return {}

    def force_law(self, ctx: Context) -> ForceLaw | None:
        """Its free-flight force per unit mass (None: it exerts none on a free object)."""
        return None


def _with_effect(scene: Scene, effect: DeclaredEffect) -> Scene:
    result = copy.deepcopy(scene)
    result.effects = [e for e in result.effects if e.name != effect.name] + [effect]
    return Scene(result.objects, result.gripper, result.extra, result.ground, result.effects)


def _with_ground(scene: Scene, **changes: object) -> Scene:
    result = copy.deepcopy(scene)
    return Scene(result.objects, result.gripper, result.extra, replace(result.ground, **changes),
                 result.effects)


class PerObjectEffect(Candidate):
    """A simulator effect with one per-object parameter, added for the moving objects."""

    param: ClassVar[str] = ""
    probe: ClassVar[float] = 1.0
    upper: ClassVar[float] = 1.0e3

    def label(self, name: str) -> str:
        return f"{self.name}.{self.param}[{name}]"

    def applicable(self, ctx: Context) -> bool:
        return super().applicable(ctx) and bool(ctx.moving_names)

    def knobs(self, ctx: Context) -> list[Knob]:
        return [Knob(self.label(n), 0.0, self.probe, 0.0, self.upper) for n in ctx.moving_names]

    def declare(self, scene: Scene, values: dict[str, float], ctx: Context) -> Scene:
        per_object = {n: float(values.get(self.label(n), 0.0)) for n in ctx.moving_names}
        return _with_effect(scene, DeclaredEffect(self.name, {self.param: per_object}))

    def free(self, ctx: Context) -> tuple[list[str], dict[str, set[str]]]:
        full = f"{self.name}.{self.param}"
        return [full], {n: {full} for n in ctx.static_names}

    def read(self, estimates: Estimates, prediction: Prediction, ctx: Context) -> dict[str, float]:
        full = f"{self.name}.{self.param}"
        return {self.label(o.name): o.params[full] for o in estimates.objects if full in o.params}

    @staticmethod
    def acceleration(v: np.ndarray) -> np.ndarray | None:
        """(n, 3) acceleration per unit coefficient at velocities ``v`` (None: no free-flight force)."""
        return None

    def force_law(self, ctx: Context) -> ForceLaw | None:
        if self.acceleration(np.zeros((1, 3))) is None:
            return None
        movers = [k for k, m in enumerate(ctx.moving) if m]

        def columns(k: int, x: np.ndarray, v: np.ndarray) -> np.ndarray:
            out = np.zeros(x.shape + (len(movers),))
            if k in movers:
                out[..., movers.index(k)] = self.acceleration(v)
            return out

        knobs = self.knobs(ctx)
        return ForceLaw([k.label for k in knobs], np.array([k.lower for k in knobs]),
                        np.array([k.upper for k in knobs]), columns)


class QuadraticDragCandidate(PerObjectEffect):
    name = "drag"
    param = "coefficient"
    probe = 0.5
    doc = "quadratic air drag a = -c |v| v, c per moving object (1/m)"
    signature = "deceleration along the velocity, growing with speed squared (fast flight)"

    @staticmethod
    def acceleration(v: np.ndarray) -> np.ndarray:
        return -np.linalg.norm(v, axis=-1, keepdims=True) * v


class LinearDragCandidate(PerObjectEffect):
    name = "linear_drag"
    param = "coefficient"
    probe = 0.5
    doc = "linear drag a = -c v, c per moving object (1/s)"
    signature = "deceleration along the velocity, proportional to speed"

    @staticmethod
    def acceleration(v: np.ndarray) -> np.ndarray:
        return -v


class DampingCandidate(PerObjectEffect):
    name = "damping"
    param = "viscosity"
    probe = 20.0
    upper = 1.0e5
    doc = "Kelvin-Voigt velocity damping per moving object (Pa*s)"
    signature = "deformation (rebound, wobble) dying out faster than the material alone allows"


class WindCandidate(Candidate):
    name = "wind"
    doc = "uniform horizontal acceleration (m/s^2): a steady wind, or gravity tilted off vertical"
    signature = "constant horizontal acceleration, in flight and while sliding"
    LABELS = ("wind.a[0]", "wind.a[1]")

    def knobs(self, ctx: Context) -> list[Knob]:
        return [Knob(label, 0.0, 0.5, -20.0, 20.0) for label in self.LABELS]

    def declare(self, scene: Scene, values: dict[str, float], ctx: Context) -> Scene:
        a = [float(values.get(label, 0.0)) for label in self.LABELS] + [0.0]
        return _with_effect(scene, DeclaredEffect(self.name, {"a": a}))

    def free(self, ctx: Context) -> tuple[list[str], dict[str, set[str]]]:
        return list(self.LABELS), {}

    def read(self, estimates: Estimates, prediction: Prediction, ctx: Context) -> dict[str, float]:
        return {label: estimates.scene[label] for label in self.LABELS}

    def force_law(self, ctx: Context) -> ForceLaw:
        knobs = self.knobs(ctx)

        def columns(k: int, x: np.ndarray, v: np.ndarray) -> np.ndarray:
            out = np.zeros(x.shape + (2,))
            out[:, 0, 0] = out[:, 1, 1] = 1.0
            return out

        return ForceLaw(list(self.LABELS), np.array([k.lower for k in knobs]),
                        np.array([k.upper for k in knobs]), columns)


class FloorTiltCandidate(Candidate):
    name = "floor_tilt"
    doc = "the floor's normal tilted to (nx, ny, 1) (normalised)"
    signature = "downhill acceleration only while touching the floor"
    LABELS = ("ground.normal[0]", "ground.normal[1]")
    QUANTUM = 0.005
    """Step of the normal's components to which the observations' floor is rounded (0.29 degrees:
    the cut moves by 2.5 mm at 0.5 m from the origin); remade observations are cached per step."""

    def applicable(self, ctx: Context) -> bool:
        return ctx.scene.ground is not None and ctx.scene.ground.normal is None

    def knobs(self, ctx: Context) -> list[Knob]:
        return [Knob(label, 0.0, 0.15, -0.7, 0.7) for label in self.LABELS]

    def declare(self, scene: Scene, values: dict[str, float], ctx: Context) -> Scene:
        normal = [float(values.get(label, 0.0)) for label in self.LABELS] + [1.0]
        return _with_ground(scene, normal=normal)

    def free(self, ctx: Context) -> tuple[list[str], dict[str, set[str]]]:
        return list(self.LABELS), {}

    def read(self, estimates: Estimates, prediction: Prediction, ctx: Context) -> dict[str, float]:
        return {label: estimates.scene[label] for label in self.LABELS}

    def reobserve(self, values: dict[str, float], ctx: Context) -> dict[str, object]:
        if ctx.reobserver is None or ctx.scene.ground.height is None:
            return {}  # no recording to remake, or no declared floor that cuts
        rounded = {label: round(values.get(label, 0.0) / self.QUANTUM) * self.QUANTUM for label in self.LABELS}
        if not any(rounded.values()):
            return {}
        return {"ground": self.declare(ctx.scene, rounded, ctx).ground}


def tilt_degrees(values: dict[str, float]) -> float:
    """Tilt angle (deg) of the floor normal (nx, ny, 1) of ``FloorTiltCandidate`` values."""
    nx, ny = (values.get(label, 0.0) for label in FloorTiltCandidate.LABELS)
    return math.degrees(math.atan(math.hypot(nx, ny)))


class FloorFrictionCandidate(Candidate):
    name = "floor_friction"
    doc = "the floor's Coulomb friction differs from the declared value"
    signature = "deceleration along the sliding direction while on the floor"
    LABEL = "ground.friction"

    def applicable(self, ctx: Context) -> bool:
        return ctx.scene.ground is not None and ctx.scene.ground.friction is not None

    def knobs(self, ctx: Context) -> list[Knob]:
        declared = ctx.scene.ground.friction
        return [Knob(self.LABEL, declared, 0.1, 0.0, 5.0)]

    def declare(self, scene: Scene, values: dict[str, float], ctx: Context) -> Scene:
        return _with_ground(scene, friction=float(values[self.LABEL]))

    def free(self, ctx: Context) -> tuple[list[str], dict[str, set[str]]]:
        return [self.LABEL], {}

    def read(self, estimates: Estimates, prediction: Prediction, ctx: Context) -> dict[str, float]:
        return {self.LABEL: estimates.scene[self.LABEL]}


class CameraTimeOffsetCandidate(Candidate):
    """A sensor effect: one camera's frames show the scene at t + offset under stamp t.

    One knob per camera (s); only differences between cameras are observable (a common offset
    is a shift of the time origin, which the fit absorbs), so values are taken relative to the
    median camera. Its signature is that of the observations, not of the motion: the probe
    remakes stages 1-2 with the camera's frames taken one set earlier (``Reobserver``). The
    refit fits the motion on observations corrected to the nearest whole frame; the offset
    itself is then fitted to a fiftieth of a frame on each camera's silhouettes against the
    refitted twin (``residual.camera_time_offset``). Needs the recording (a ``Reobserver``) and
    at least ``MIN_CAMERAS`` cameras (with two, an offset of one is an offset of the other).
    """

    name = "camera_time_offset"
    doc = "a camera's frames show the scene at t + offset (s) under stamp t (badly synchronised)"
    signature = ("one camera's silhouettes lead or lag the others': the carved volume shrinks and "
                 "its centroid shifts along the motion")
    sensor = True
    MIN_CAMERAS = 3
    MAX_FRAMES = 1
    """Largest offset tried, in frames (the fit of the offset searches half a frame beyond)."""

    def label(self, camera: str) -> str:
        return f"{self.name}[{camera}]"

    def applicable(self, ctx: Context) -> bool:
        return (super().applicable(ctx) and ctx.reobserver is not None
                and len(ctx.views) >= self.MIN_CAMERAS)

    def knobs(self, ctx: Context) -> list[Knob]:
        span = self.MAX_FRAMES * ctx.frame_dt
        return [Knob(self.label(v.name), 0.0, ctx.frame_dt, -span, span) for v in ctx.views]

    def relative(self, values: dict[str, float], ctx: Context) -> dict[str, float]:
        """Each camera's offset minus the median camera's."""
        offsets = {v.name: float(values.get(self.label(v.name), 0.0)) for v in ctx.views}
        median = float(np.median(list(offsets.values())))
        return {camera: offset - median for camera, offset in offsets.items()}

    def shifts(self, values: dict[str, float], ctx: Context) -> dict[str, int]:
        """Whole frames by which each camera leads the median camera."""
        return {c: int(round(o / ctx.frame_dt)) for c, o in self.relative(values, ctx).items()}

    def declare(self, scene: Scene, values: dict[str, float], ctx: Context) -> Scene:
        offsets = {c: o for c, o in self.relative(values, ctx).items() if o != 0.0}
        return _with_effect(scene, DeclaredEffect(self.name, {"offset": offsets}))

    def free(self, ctx: Context) -> tuple[list[str], dict[str, set[str]]]:
        return [], {}

    def reobserve(self, values: dict[str, float], ctx: Context) -> dict[str, object]:
        shifts = self.shifts(values, ctx)
        return {"shifts": shifts} if any(shifts.values()) else {}

    def read(self, estimates: Estimates, prediction: Prediction, ctx: Context) -> dict[str, float]:
        span = (self.MAX_FRAMES + 0.5) * ctx.frame_dt
        fitted = {self.label(v.name): camera_time_offset(prediction, ctx.given.frames, v, span,
                                                         ctx.frame_dt / 50, ctx.device)
                  for v in ctx.views}
        return {self.label(c): o for c, o in self.relative(fitted, ctx).items()}


class HeldCandidate(Candidate):
    """A named effect held at the values free flight measured: its refit fits the materials only.

    Where free flight shows a force a named effect's law explains, but the refit with the
    effect's knobs free does not predict the held-out frames (a small budget can trade the
    knobs against the materials), the loop tries the effect again with its knobs held at free
    flight's values, which no material can absorb. It names the same effect.
    """

    def __init__(self, inner: Candidate, values: dict[str, float]) -> None:
        self.inner, self.values = inner, dict(values)
        self.name, self.signature, self.sensor = inner.name, inner.signature, inner.sensor
        self.doc = f"{inner.doc} (held at the values free flight measured)"

    def applicable(self, ctx: Context) -> bool:
        return self.inner.applicable(ctx)

    def knobs(self, ctx: Context) -> list[Knob]:
        return self.inner.knobs(ctx)

    def declare(self, scene: Scene, values: dict[str, float], ctx: Context) -> Scene:
        return self.inner.declare(scene, values, ctx)

    def free(self, ctx: Context) -> tuple[list[str], dict[str, set[str]]]:
        return [], {}

    def read(self, estimates: Estimates, prediction: Prediction, ctx: Context) -> dict[str, float]:
        return dict(self.values)

    def reobserve(self, values: dict[str, float], ctx: Context) -> dict[str, object]:
        return self.inner.reobserve(values, ctx)

    def force_law(self, ctx: Context) -> ForceLaw | None:
        return self.inner.force_law(ctx)


class FieldCandidate(Candidate):
    """A smooth force field fitted in free flight (``freeflight.sparse_field``): not in the library.

    What the loop offers when free flight shows a force that no named effect explains: the
    field's terms at their free-flight values (fixed in its refit), as the simulator's
    ``ForceField``. It describes the force; it does not name a cause.
    """

    name = "force_field"
    doc = "unmodelled external force: a smooth field a(x, v) fitted in free flight, not a named effect"
    signature = "a force in free flight that no named effect explains"

    def __init__(self, terms: list[tuple[int, int]], origin: np.ndarray, values: dict[str, float]) -> None:
        self.terms, self.origin, self.values = list(terms), np.asarray(origin, dtype=float), dict(values)
        self.law = field_law(self.origin, self.terms)

    def knobs(self, ctx: Context) -> list[Knob]:
        return [Knob(label, 0.0, 1.0, -FIELD_BOUND, FIELD_BOUND) for label in self.law.labels]

    def declare(self, scene: Scene, values: dict[str, float], ctx: Context) -> Scene:
        w = np.zeros(3 * len(FIELD_FEATURES))
        for label in self.law.labels:
            w[int(label[label.index("[") + 1: -1])] = float(values.get(label, 0.0))
        return _with_effect(scene, DeclaredEffect(self.name, {"w": w.tolist(), "origin": self.origin.tolist()}))

    def free(self, ctx: Context) -> tuple[list[str], dict[str, set[str]]]:
        return [], {}

    def read(self, estimates: Estimates, prediction: Prediction, ctx: Context) -> dict[str, float]:
        return dict(self.values)

    def force_law(self, ctx: Context) -> ForceLaw:
        return self.law

    def describe(self) -> list[str]:
        """Its terms as 'a_y = 1.47 * 1 m/s^2'-style lines."""
        return [f"a_{'xyz'[axis]} += {self.values[label]:.4g} * {FIELD_FEATURES[feature]}"
                for (feature, axis), label in zip(self.terms, self.law.labels, strict=True)]


LIBRARY: tuple[Candidate, ...] = (QuadraticDragCandidate(), LinearDragCandidate(), WindCandidate(),
                                  FloorTiltCandidate(), FloorFrictionCandidate(), DampingCandidate(),
                                  CameraTimeOffsetCandidate())
"""Every candidate the loop tries, in this order when they explain equally well."""
