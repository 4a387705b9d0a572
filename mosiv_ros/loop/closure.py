"""The loop closure: fit, find the residual, trace it to a missing effect, add it, refit, repeat.

``LoopClosure(frames, lifted, scene, identify_config, loop_config).run()`` on stages 1-2's
output (``mosiv_ros.loop.report.close_loop`` runs it on a bag):

1. Split the frames: the first ``1 - holdout`` are fitted, the rest are held out (never fitted;
   they decide whether an effect is accepted). The split is by stamp: a model on observations
   remade for a sensor effect (``loop.observations``; a camera time offset) is fitted and
   scored on the same stamps, against its own observations.
2. Fit the declared model (``identify.run.fit_problem``) and roll its twin over every frame. An
   object whose family the scene leaves open gets the family ``identify.family`` chooses on the
   fitted frames, once, before this first fit; every later model keeps it. Measure the
   free-flight evidence of the fitted frames (``loop.freeflight``): in flight the centre of mass
   shows the external force, whatever the materials, so a fit cannot hide an effect there.
3. Analyse the residual (``loop.residual``). The evidence vector is the centroid residual of
   every object and frame (divided by ``centroid_noise``) and the radius-of-gyration residual
   (divided by ``shape_noise``), all frames after the first. What a refit of the same model
   can absorb is projected out first: per object and axis, a constant and a term linear in
   time (the position and initial velocity are refitted). If the rest has a mean square of
   at most ``significance`` (in units of the noise) *and* free flight shows no force beyond
   the model's (a fit can hide an effect in its materials and initial velocities; a flight
   cannot), there is nothing to explain: stop.
4. Rank the library's candidates (``loop.library``) by how much of that rest their signature
   explains: each knob is switched on by its probe step alone in the current twin (a sensor
   effect's: in the observations), the change of the evidence per unit of the knob is one
   column, and a bounded least-squares fit (knobs inside their ranges, the nuisance terms free)
   gives the explained fraction R^2 = 1 - |rest after| ^2 / |rest before|^2 and a first
   estimate of each knob. Then free flight weighs in (``weigh_flight``): where it shows a force
   the current model lacks, the candidates are those whose force law explains at least
   ``min_explained`` of it there, in order of their free-flight AIC (a law more than
   ``AIC_GAP`` behind the best is dropped), with the knob values and initial velocities free
   flight gives them; an effect with no free-flight force (a floor's, damping, a sensor's) waits
   for a later round. Where free flight shows no force, a force-law candidate whose first
   estimate would have shown there is ruled out.
5. Refit the current model with no new effect (the control: a better fit alone is never
   credited to an effect; if it beats the current model it becomes the current model). Where
   free flight shows the force, warm-started and given a candidate's budget (free flight is the
   evidence, the control measures the fit's spread); elsewhere afresh, by the very procedure of
   a candidate's refit (search and curriculum from the defaults), so that what a new search
   finds is not credited to the effect it was run with. Refit also the model with each of the
   ``top_k`` leading candidates whose R^2 reaches ``min_explained`` (the effect's knobs start at
   their first estimate, the objects' parameters afresh, as in the first fit; a sensor effect's
   model on its corrected observations), and roll out each twin.
6. **Acceptance**: a candidate with p knobs is accepted when its held-out centroid error E_new
   (RMS over the held-out frames and objects) satisfies
   E_new <= margin * exp(-penalty * p) * E_current
   (defaults 0.8 and 0.1: a one-knob effect must cut the held-out error by 28 %, a two-knob one
   by 35 %), E_current the better of the current model and its control; equivalently its
   penalised score ln E + penalty * p beats the current model's by ln(1 / margin), and, as
   nothing but the residual speaks for it, its model must leave at most ``explains`` times
   ``significance`` of it (an effect that shrinks a residual many times the noise, where a
   recording from another engine or a missing effect elsewhere leaves the model wrong, is not
   named for it). Of several accepted, the lowest held-out error wins. Where free flight shows
   the force and the candidate's law explains it there, that is the evidence for the effect, and the refit need
   only predict the held-out frames no worse than the material-only models do, within their
   spread (``spread_limit``: E_new at most the larger of the current model's and its control's
   plus their difference, how far refits of one model land apart on these frames): a fit that
   already hides an effect in
   its materials and initial velocities can predict frames where the effect no longer acts (an
   object come to rest) as well as one with it. Of several such, free flight's AIC picks. Each
   model's AIC and BIC on the fitted frames (``information``) are reported beside.
7. Repeat from 3 with the accepted effect in the model, at most ``max_rounds`` times.

Verdicts: ``nothing to explain`` (the first residual is at the noise level), ``explained``
(effects were accepted and the residual is at the noise level), ``unexplained`` (no candidate's
signature reaches ``min_explained``, or none of the refits pays for itself: the residual is
reported, not attributed to the nearest effect), ``partly explained`` (effects were accepted,
but what is left is still above the noise and nothing explains it), ``unmodelled external
force`` (free flight shows a force no named effect explains, and a smooth field of few terms
fitted there, ``try_field``, pays for itself by the same criterion: the force is described,
not named; unless the field is a named law free flight shows, ``name_field``, which is then
accepted under its name).

What it is for: ``mosiv close-loop`` and identify_node's ``close_loop`` option.
What it is not for: the report files (``loop.report``).
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.optimize import lsq_linear
from scipy.stats import chi2

from mosiv_ros.config import HOLDOUT, IdentifyConfig
from mosiv_ros.identify.estimates import Estimates
from mosiv_ros.identify.family import FamilyChoice, select_families, with_family_scores
from mosiv_ros.identify.fit import FitProblem, FitSettings, Identifier
from mosiv_ros.identify.observations import View
from mosiv_ros.identify.problem import build_problem
from mosiv_ros.identify.run import (
    Identification,
    fit_problem,
    phase_progress,
    problem_options,
)
from mosiv_ros.io.scene import Scene
from mosiv_ros.lifting.lift import LiftedParticles
from mosiv_ros.loop.freeflight import (
    P_VALUE,
    SAME_LAW,
    TIE,
    ForceLaw,
    FreeFlight,
    as_law,
    combine,
    field_law,
    free_flight,
    sparse_field,
)
from mosiv_ros.loop.library import LIBRARY, Candidate, Context, FieldCandidate, HeldCandidate
from mosiv_ros.loop.observations import Observations, Reobserver
from mosiv_ros.loop.residual import Floor, ResidualAnalysis, analyse
from mosiv_ros.predict.twin import Prediction
from mosiv_ros.progress import Progress
from mosiv_ros.recon.reconstruct import ObservedFrame
from mosiv_ros.sim.errors import SimulationError
from mosiv_ros.sim.materials import MATERIAL_PARAM_NAMES
from mosiv_ros.sim.runtime import resolve_device
from mosiv_ros.simulation import OFFSET

_LOG = logging.getLogger(__name__)

AIC_GAP = 10.0
"""A force law whose free-flight AIC exceeds the best's by more than this is not refitted
(Burnham and Anderson: essentially no support)."""
NOTHING, EXPLAINED, UNEXPLAINED, PARTLY, UNMODELLED = (
    "nothing to explain", "explained", "unexplained", "partly explained", "unmodelled external force")


@dataclass
class LoopConfig:
    """Settings of the loop closure (see the module docstring for each one's role)."""

    holdout: float = HOLDOUT
    top_k: int = 2
    min_explained: float = 0.5
    significance: float = 1.0
    centroid_noise: float = 0.002
    shape_noise: float = 0.002
    margin: float = 0.8
    penalty: float = 0.1
    max_rounds: int = 3
    explains: float = 3.0
    """A candidate free flight does not show is accepted only if its model leaves the residual at
    most this many times ``significance`` (it must explain the residual, not only shrink it)."""
    moving_threshold: float = 0.01
    """Least observed centroid travel (m) for an object to count as moving."""
    contact_tolerance: float = 0.01
    silhouettes: bool = True
    """Per-camera silhouette residuals in the analysis (descriptive only)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.holdout < 1.0:
            raise ValueError(f"holdout must be in (0, 1), got {self.holdout}")
        if self.top_k < 1 or self.max_rounds < 1:
            raise ValueError(f"top_k and max_rounds must be >= 1, got {self.top_k}, {self.max_rounds}")
        if not 0.0 < self.margin <= 1.0 or self.penalty < 0:
            raise ValueError(f"margin must be in (0, 1] and penalty >= 0, got {self.margin}, {self.penalty}")
        if self.centroid_noise <= 0 or self.shape_noise <= 0:
            raise ValueError("centroid_noise and shape_noise must be positive")
        if self.explains < 1.0:
            raise ValueError(f"explains must be >= 1 (a multiple of significance), got {self.explains}")

    def threshold(self, knobs: int) -> float:
        """Largest held-out error ratio (new / current) that accepts an effect of ``knobs`` knobs."""
        return self.margin * math.exp(-self.penalty * knobs)


@dataclass
class Model:
    """One fitted model: the effects it adds to the declaration, their fitted values, its twin."""

    effects: list[tuple[Candidate, dict[str, float]]]
    scene: Scene
    observations: Observations
    estimates: Estimates
    identification: Identification
    prediction: Prediction
    analysis: ResidualAnalysis
    seconds: float
    information: dict[str, float] = field(default_factory=dict)
    """AIC and BIC on the fitted frames (``LoopClosure.information``)."""

    @property
    def names(self) -> list[str]:
        return [c.name for c, _ in self.effects]

    @property
    def held_out_error(self) -> float:
        return self.analysis.errors()["held_out"]


@dataclass
class Flight:
    """What the free-flight evidence says of a candidate (``loop.freeflight``).

    ``explained``: the share of the current model's free-flight excess its force law removes;
    ``aic``: chi-square plus twice the knobs; ``values`` / ``std``: its knobs fitted there.
    """

    explained: float
    chi2: float
    aic: float
    values: dict[str, float]
    std: dict[str, float]


@dataclass
class Ranked:
    """A candidate's ranking: explained fraction, first knob estimates, and its refit, if any.

    ``explained`` is the share of the simulated residual its signature explains; ``flight`` what
    free flight says (None: it exerts no force there, or there is no free flight); ``velocity``
    (K, 3) the initial velocities its refit starts from (NaN rows: from the first frames).
    """

    candidate: Candidate
    explained: float
    estimate: dict[str, float]
    refit: Model | None = None
    ratio: float = math.nan
    threshold: float = math.nan
    accepted: bool = False
    note: str = ""
    flight: Flight | None = None
    ruled_out: bool = False
    velocity: np.ndarray | None = None


@dataclass
class Round:
    significance: float
    ranking: list[Ranked] = field(default_factory=list)
    accepted: str = ""
    flight_force: bool = False
    """A force the current model lacks acts in free flight: only force laws may explain it."""
    control: Model | None = None
    """The current model refitted with a candidate's budget and no new effect."""


@dataclass
class LoopResult:
    before: Model
    after: Model
    rounds: list[Round]
    verdict: str
    window: int
    config: LoopConfig
    seconds: float
    families: list[FamilyChoice] = field(default_factory=list)
    """The families chosen for objects the scene leaves open (empty: every one declared)."""
    flight: FreeFlight | None = None
    """The free-flight evidence of the fitted frames."""


class LoopError(ValueError):
    """The loop cannot run on this input (too few frames to hold any out, no objects)."""


class LoopClosure:
    """The loop on one recording's stages 1-2 output (see the module docstring).

    ``progress(phase, done, total, unit)`` follows every fit (``identify.run.phase_progress``).
    ``reobserver`` (stages 1-2 of the recording, remade on demand) lets the library's sensor
    effects correct the observations; without it they are not tried.

    With ``identify.checkpoint_dir`` set, every fit of the loop checkpoints in a folder of its
    own under it (``round1-drag``, ...), so that a rerun of the same loop on the same recording
    resumes each fit where it stopped and takes the finished ones as they ended.

    The frames from ``stamp_ns`` of the ``window``-th given frame on are held out; a model
    whose observations were remade (a sensor effect) is scored on the same stamps.
    """

    def __init__(self, frames: Sequence[ObservedFrame], lifted: LiftedParticles, scene: Scene,
                 identify: IdentifyConfig, loop: LoopConfig | None = None,
                 views: Sequence[View] = (), gripper_poses: Sequence[tuple[int, np.ndarray]] = (),
                 library: Sequence[Candidate] = LIBRARY,
                 progress: Progress | None = None,
                 reobserver: Reobserver | None = None) -> None:
        self.loop = loop or LoopConfig()
        frames = sorted((f for f in frames if f.stamp_ns >= lifted.stamp_ns), key=lambda f: f.stamp_ns)
        self.given = Observations(frames, lifted)
        self.window = int(round(len(frames) * (1 - self.loop.holdout)))
        if self.window < 3 or self.window >= len(frames):
            raise LoopError(f"{len(frames)} frames with holdout {self.loop.holdout}: need at "
                            "least 3 fitted and 1 held-out frame")
        self.held_out_ns = frames[self.window].stamp_ns
        self.scene, self.identify, self.reobserver = scene, identify, reobserver
        self.views, self.gripper_poses = list(views), list(gripper_poses)
        self.library, self.progress = list(library), progress
        self.families: list[FamilyChoice] = []
        self.flight: FreeFlight | None = None
        self.round = 0
        self.floor = Floor.of(scene)
        self.device = resolve_device(identify.device)
        """Where the residual's silhouettes render: the fit's device (torch's, a GPU or the CPU)."""

    # --- models ------------------------------------------------------------------------------

    def context(self, model: Model) -> Context:
        centroids = model.analysis.observed
        travel = np.nanmax(np.linalg.norm(centroids - centroids[:1], axis=-1), axis=0)
        moving = [bool(t > self.loop.moving_threshold) for t in np.nan_to_num(travel)]
        times = model.prediction.times
        return Context(list(model.prediction.names), moving, model.scene, float(times[1] - times[0]),
                       self.views, self.given, self.reobserver, self.device)

    def fitted_frames(self, observations: Observations) -> int:
        """How many of ``observations``' frames come before the held-out stamps."""
        return sum(f.stamp_ns < self.held_out_ns for f in observations.frames)

    def observations(self, effects: Sequence[tuple[Candidate, dict[str, float]]],
                     ctx: Context | None) -> Observations:
        """The given observations, or those remade as the ``effects`` at their values change them."""
        changes: dict[str, object] = {}
        for candidate, values in effects:
            changes.update(candidate.reobserve(values, ctx) if ctx is not None else {})
        return ctx.reobserver.observe(**changes) if changes else self.given

    def problem(self, scene: Scene, effects: Sequence[Candidate], ctx: Context | None,
                observations: Observations) -> FitProblem:
        """The fit problem of ``scene`` over the fitted frames, with the effects' knobs free.

        The simulation domain covers every frame (held-out ones too), so that one domain serves
        the fit and the rollouts over the whole recording.
        """
        options = problem_options(self.identify, self.views)
        options.families = {c.id: c.family for c in self.families}
        problem = build_problem(observations.frames, observations.lifted, scene, self.views,
                                self.gripper_poses, options)
        problem.observations = problem.observations.select(slice(0, self.fitted_frames(observations)))
        problem.sim_config.device = self.identify.device
        for candidate in effects:
            free, fixed = candidate.free(ctx)
            problem.free += [name for name in free if name not in problem.free]
            for name, params in fixed.items():
                problem.fixed.setdefault(name, set()).update(params)
        return problem

    def declared(self, effects: Sequence[tuple[Candidate, dict[str, float]]], ctx: Context | None) -> Scene:
        """The declared scene with each of ``effects`` declared at its values, in order."""
        scene = self.scene
        for candidate, values in effects:
            scene = candidate.declare(scene, values, ctx)
        return scene

    def fit(self, effects: list[tuple[Candidate, dict[str, float]]], ctx: Context | None,
            label: str, key: str, velocity: np.ndarray | None = None, warm: Model | None = None,
            start: Observations | None = None, follow: bool = True) -> Model:
        """Fit the declared model plus ``effects`` (knobs at their initial values).

        The objects' parameters start afresh (at the simulator's defaults), as in the first fit:
        a fit without the missing effect distorts them, and its values are a poor start.
        ``velocity`` (K, 3; NaN rows: estimate from the first frames) starts the initial
        velocities. ``warm``: a fit of the same model to continue from (no search), the control
        of an acceptance. ``key``: the fit's checkpoint folder within the round's.

        The fit is on ``start``, by default the observations the effects' values make
        (``observations``). Where its fitted values make other ones (a tilted floor fitted to
        another tilt cuts them elsewhere; a camera offset fitted to another whole frame), and
        ``follow``, it continues once on those, from where it ended.
        """
        tick = time.perf_counter()
        identify = self.identify
        if identify.checkpoint_dir:
            identify = replace(identify, checkpoint_dir=str(Path(identify.checkpoint_dir) / f"round{self.round}-{key}"))
        observations = start or self.observations(effects, ctx)
        problem = self.problem(self.declared(effects, ctx), [c for c, _ in effects], ctx, observations)
        problem.initial_velocity = velocity
        if warm is not None:
            result = warm.identification.result
            problem.warm_start = (result.u, result.velocity)
        identification = fit_problem(problem, identify,
                                     phase_progress(self.progress, label),
                                     self.fitted_frames(observations))
        with_family_scores(identification.estimates, self.families)
        prediction = rollout(identification.identifier, observations)
        fitted = [(c, c.read(identification.estimates, prediction, ctx)) for c, _ in effects]
        closed = self.declared(fitted, ctx)
        analysis = self.analyse(prediction, observations)
        _LOG.info("%s: held-out centroid error %.2f mm (fitted frames %.2f mm), %s", label,
                  analysis.errors()["held_out"] * 1e3, analysis.errors()["fitted"] * 1e3,
                  ", ".join(f"{k}={v:.4g}" for _, values in fitted for k, v in values.items()) or "declared model")
        model = Model(fitted, closed, observations, _material_estimates(identification.estimates),
                      identification, prediction, analysis, time.perf_counter() - tick)
        model.information = self.information(model)
        if follow and self.observations(fitted, ctx) is not observations:
            _LOG.info("%s: its fitted values remake the observations; fitting on those", label)
            followed = self.fit(fitted, ctx, f"{label}, observations remade", f"{key}-remade",
                                warm=model, follow=False)
            followed.seconds += model.seconds
            return followed
        return model

    def probe(self, model: Model, scene: Scene, ctx: Context) -> Prediction:
        """``model`` with ``scene``'s declaration instead of its own, rolled out unfitted."""
        problem = self.problem(scene, [], ctx, model.observations)
        _start_at(problem, model.estimates)
        identifier = Identifier(problem, FitSettings.of(self.identify))
        identifier.start_from(model.identification.identifier.offsets, model.identification.result.velocity)
        return rollout(identifier, model.observations)

    def analyse(self, prediction: Prediction, observations: Observations) -> ResidualAnalysis:
        views = self.views if self.loop.silhouettes else ()
        return analyse(observations.frames, prediction, self.fitted_frames(observations), self.floor,
                       views, self.loop.contact_tolerance, self.device)

    def free_flight(self, model: Model, observations: Observations | None = None) -> FreeFlight:
        """The free-flight evidence of the fitted frames of ``observations`` (default: the given).

        Free means clear of the floor, the other objects and the gripper by the reconstruction's
        voxel plus the model's grid spacing (its contact reach).
        """
        problem = model.identification.identifier.problem
        observations = observations or self.given
        frames = observations.frames[: self.fitted_frames(observations)]
        voxel = max((g.voxel_size for f in frames for g in f.objects.values()), default=0.0)
        gravity = next(e.initial["g"] for e in problem.sim_config.effects if e.name == "gravity")
        times = np.array([(f.stamp_ns - frames[0].stamp_ns) * 1e-9 for f in frames])
        return free_flight(frames, list(model.prediction.object_ids), times, self.floor, gravity,
                           voxel + problem.sim_config.dx, problem.sim_config.colliders, self.views)

    def information(self, model: Model) -> dict[str, float]:
        """AIC and BIC of a model from its fitted frames' evidence (noise units) and its parameters.

        n residuals r (centroid and shape, frames 1 .. fitted - 1), p = free parameters plus six
        initial-velocity components per object: AIC = n ln(|r|^2 / n) + 2 p, BIC = n ln(|r|^2 / n)
        + p ln n. Lower is better; a difference below 2 says little, above 10 much.
        """
        fitted = self.fitted_frames(model.observations)
        n_frames, n_objects = len(model.prediction.times), len(model.prediction.object_ids)
        r = self.evidence(model.prediction, model.observations.frames)
        keep = np.zeros((n_frames - 1, n_objects, 4), dtype=bool)
        keep[: fitted - 1] = True
        centroid = keep[..., :3].ravel()
        shape = keep[..., 3].ravel()
        r = r[np.concatenate([centroid, shape])]
        r = r[np.isfinite(r)]
        n = len(r)
        p = len(model.identification.identifier.entries) + 6 * n_objects
        rss = max(float(r @ r), 1e-12)
        return {"aic": n * math.log(rss / n) + 2 * p, "bic": n * math.log(rss / n) + p * math.log(n),
                "n": n, "p": p}

    # --- evidence and ranking ----------------------------------------------------------------

    def evidence(self, prediction: Prediction, frames: Sequence[ObservedFrame]) -> np.ndarray:
        """The evidence of a prediction: its centroid and shape residuals in noise units.

        On the prediction's frames; where ``frames`` has no frame at a stamp, NaN.
        """
        by_stamp = {f.stamp_ns: f for f in frames}
        tolerance = int(0.25 * (prediction.times[1] - prediction.times[0]) * 1e9)
        aligned = []
        for stamp in prediction.stamps_ns():
            near = [s for s in by_stamp if abs(s - stamp) <= tolerance]
            aligned.append(by_stamp[near[0]] if near else ObservedFrame(stamp, {}))
        analysis = analyse(aligned, prediction, 0, self.floor, (), self.loop.contact_tolerance)
        return np.concatenate([(analysis.centroid[1:] / self.loop.centroid_noise).ravel(),
                               (analysis.shape[1:] / self.loop.shape_noise).ravel()])

    def nuisance(self, n_frames: int, n_objects: int) -> np.ndarray:
        """Columns a refit absorbs: per object and axis a constant and a linear term.

        Those are for the centroid block (frames after the first); the shape block gets a
        constant per object.
        """
        n = n_frames - 1
        t = np.arange(1, n + 1, dtype=np.float64) / n
        columns = []
        size = n * n_objects * 3 + n * n_objects
        for k in range(n_objects):
            for axis in range(3):
                for basis in (np.ones(n), t):
                    column = np.zeros((n, n_objects, 3))
                    column[:, k, axis] = basis
                    columns.append(np.concatenate([column.ravel(), np.zeros(n * n_objects)]))
            column = np.zeros((n, n_objects))
            column[:, k] = 1.0
            columns.append(np.concatenate([np.zeros(n * n_objects * 3), column.ravel()]))
        return np.stack(columns, axis=1) if columns else np.zeros((size, 0))

    def rest(self, model: Model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(evidence, nuisance columns, rows used) of a model."""
        r = self.evidence(model.prediction, model.observations.frames)
        N = self.nuisance(len(model.prediction.times), len(model.prediction.object_ids))
        rows = np.isfinite(r)
        return r, N, rows

    def significance(self, model: Model) -> float:
        """Mean square of the evidence beyond what the nuisance terms absorb (noise units)."""
        r, N, rows = self.rest(model)
        if not rows.any():
            return 0.0
        coef = np.linalg.lstsq(N[rows], r[rows], rcond=None)[0]
        left = r[rows] - N[rows] @ coef
        return float(np.mean(left**2))

    def rank(self, candidate: Candidate, model: Model, ctx: Context) -> Ranked:
        knobs = candidate.knobs(ctx)
        r, N, rows = self.rest(model)
        columns = []
        for knob in knobs:
            values = {k.label: k.neutral for k in knobs}
            values[knob.label] = knob.neutral + knob.probe
            observed = self.sensed(model, candidate, values, ctx)
            try:  # a physical effect changes the prediction, a sensor effect the observations
                probe = (self.probe(model, candidate.declare(model.scene, values, ctx), ctx)
                         if observed is None else model.prediction)
            except SimulationError as error:
                return Ranked(candidate, 0.0, {}, note=f"probe diverged: {error}")
            frames = (observed or model.observations).frames
            # the knob moves the prediction by column * value, the residual by minus that
            columns.append((r - self.evidence(probe, frames)) / knob.probe)
        J = np.stack(columns, axis=1)
        rows = rows & np.all(np.isfinite(J), axis=1)
        A = np.concatenate([J, N], axis=1)[rows]
        lower = [k.lower - k.neutral for k in knobs] + [-np.inf] * N.shape[1]
        upper = [k.upper - k.neutral for k in knobs] + [np.inf] * N.shape[1]
        solution = lsq_linear(A, r[rows], bounds=(lower, upper))
        before = r[rows] - N[rows] @ np.linalg.lstsq(N[rows], r[rows], rcond=None)[0]
        after = r[rows] - A @ solution.x
        explained = 1.0 - float(after @ after) / max(float(before @ before), 1e-12)
        estimate = {k.label: float(np.clip(k.neutral + solution.x[i], k.lower, k.upper))
                    for i, k in enumerate(knobs)}
        return Ranked(candidate, explained, estimate)

    def flight_force(self, model: Model, ctx: Context) -> bool:
        """Free flight shows a force beyond the laws of the model's effects."""
        if self.flight is None or not self.flight.segments:
            return False
        return self.flight.acts(self.flight.fit(_laws(model.effects, ctx)))

    def weigh_flight(self, ranking: list[Ranked], current: Model, ctx: Context) -> bool:
        """Annotate ``ranking`` with the free-flight evidence; True when a force acts there.

        Where a force beyond the current model's acts in free flight, a candidate is weighed by
        the share of it its force law explains, starts its refit from the knob values and
        initial velocities free flight gives it; a sensor effect by the share its corrected
        observations remove (a badly timed camera bends the carved centroids too); any other
        candidate cannot explain it. Where none acts, a force-law candidate whose first estimate
        would have shown in free flight is ruled out.
        """
        flight = self.flight
        if flight is None or not flight.segments:
            return False
        base_law = _laws(current.effects, ctx)
        base = flight.fit(base_law)
        acting = flight.acts(base)
        for ranked in ranking:
            law = ranked.candidate.force_law(ctx)
            corrected = self.sensed(current, ranked.candidate, ranked.estimate, ctx) if acting else None
            if law is None and corrected is not None:  # a sensor effect: does its correction remove it?
                after = self.free_flight(current, corrected)
                left = after.fit(base_law) if after.segments else None
                share = (1.0 - (left.chi2 - after.chi2_flexible) / max(base.chi2 - flight.chi2_flexible, 1e-12)
                         if left is not None else 0.0)
                ranked.flight = Flight(float(np.clip(share, 0.0, 1.0)), math.nan, math.nan, {}, {})
                continue
            if law is None:
                if acting:
                    ranked.note = "free flight shows a force this effect does not exert"
                continue
            joint = combine(base_law, law)
            fit = flight.fit(joint)
            values = {label: fit.values[label] for label in law.labels}
            ranked.flight = Flight(flight.explained(fit, base), fit.chi2, fit.chi2 + 2 * len(law.labels),
                                   values, {label: fit.std[label] for label in law.labels})
            if acting:
                ranked.estimate = {**ranked.estimate, **values}
                ranked.velocity = np.full((len(ctx.names), 3), np.nan)
                for k, v in fit.initial_velocity.items():
                    ranked.velocity[k] = v
                continue
            at = flight.chi2_at(joint, {**base.values, **ranked.estimate})
            if at - base.chi2 > chi2.ppf(1.0 - P_VALUE, len(law.labels)):
                ranked.ruled_out = True
                ranked.note = (f"ruled out by free flight: at its first estimate the flights would "
                               f"show a force they do not (chi-square +{at - base.chi2:.0f})")
        return acting

    def leading(self, round_: Round) -> list[Ranked]:
        """The candidates to refit this round (see ``weigh_flight``)."""
        loop = self.loop
        if round_.flight_force:
            able = [r for r in round_.ranking
                    if r.flight is not None and r.flight.explained >= loop.min_explained]
            laws = [r for r in able if math.isfinite(r.flight.aic)]  # sensor effects have no law
            best = min((r.flight.aic for r in laws), default=math.inf)
            for r in laws:
                if r.flight.aic > best + AIC_GAP:
                    r.note = f"free flight fits it far worse than the best (AIC +{r.flight.aic - best:.0f})"
            able = [r for r in able if not r.flight.aic > best + AIC_GAP]
            return sorted(able, key=lambda r: -r.flight.explained)[: loop.top_k]
        return [r for r in round_.ranking if r.explained >= loop.min_explained and not r.ruled_out][: loop.top_k]

    # --- the loop ----------------------------------------------------------------------------

    def run(self) -> LoopResult:
        tick = time.perf_counter()
        loop = self.loop
        self.families = self.choose_families()
        before = current = self.fit([], None, "fit declared model", "declared")
        self.flight = self.free_flight(before)
        if self.flight.segments:
            _LOG.info("free flight: %d frames in %d segments; external force %.2f m/s^2 (p = %.2g): %s",
                      self.flight.frames, len(self.flight.segments), self.flight.force(self.flight.null),
                      self.flight.p_value(self.flight.null),
                      "significant" if self.flight.significant else "not significant")
        rounds: list[Round] = []
        verdict = ""
        for index in range(1, loop.max_rounds + 1):
            self.round = index  # names the round's checkpoint folders
            significance = self.significance(current)
            round_ = Round(significance)
            rounds.append(round_)
            ctx = self.context(current)
            flying = self.flight_force(current, ctx)
            _LOG.info("residual: mean square %.3g noise units (threshold %.3g)%s", significance,
                      loop.significance, "; free flight shows a force the model lacks" if flying else "")
            if significance <= loop.significance and not flying:  # a fit can hide an effect, a flight cannot
                verdict = EXPLAINED if current.effects else NOTHING
                break
            have = set(current.names)
            candidates = [c for c in self.library if c.name not in have and c.applicable(ctx)]
            round_.ranking = [self.rank(c, current, ctx) for c in candidates]
            round_.flight_force = self.weigh_flight(round_.ranking, current, ctx)
            round_.ranking.sort(key=lambda r: -_weight(r, round_.flight_force))
            _LOG.info("ranking: %s", ", ".join(_describe(r) for r in round_.ranking))
            leading = self.leading(round_)
            material_only = [current.held_out_error]
            if leading or round_.flight_force:  # the control: a candidate's budget, no new effect
                round_.control = (self.fit(current.effects, ctx, "refit without a new effect", "control",
                                           warm=current) if round_.flight_force else
                                  self.fit(current.effects, ctx, "refit afresh without a new effect",
                                           "control-afresh"))
                material_only.append(round_.control.held_out_error)
                if round_.control.held_out_error < current.held_out_error:
                    current = round_.control
            limit = spread_limit(material_only) if round_.flight_force else None
            for ranked in leading:
                self.try_candidate(ranked, current, ctx, limit)
            accepted = [r for r in leading if r.accepted]
            if not accepted:
                field = self.try_field(round_, current, ctx, limit) if round_.flight_force else None
                named = self.name_field(field, round_, ctx) if field is not None and field.accepted else None
                if named is not None:  # the field is a named law: its refit stands for that law
                    round_.accepted = named.effects[-1][0].name
                    current = named
                    continue
                if field is not None and field.accepted:
                    round_.accepted = field.candidate.name
                    current = field.refit
                    verdict = UNMODELLED
                else:
                    verdict = PARTLY if current.effects else UNEXPLAINED
                break
            # where free flight decides, its evidence picks (held-out errors this close are noise)
            best = min(accepted, key=lambda r: r.flight.aic if round_.flight_force else r.refit.held_out_error)
            round_.accepted = best.candidate.name
            current = best.refit
        else:
            settled = (self.significance(current) <= loop.significance
                       and not self.flight_force(current, self.context(current)))
            verdict = EXPLAINED if settled else PARTLY
        _LOG.info("loop closure: %s; effects added: %s", verdict, ", ".join(current.names) or "none")
        return LoopResult(before, current, rounds, verdict, self.window, loop,
                          time.perf_counter() - tick, self.families, self.flight)

    def try_field(self, round_: Round, current: Model, ctx: Context, limit: float) -> Ranked | None:
        """Free flight's force as a smooth field, where no named effect explains it, refitted.

        Its terms come from ``freeflight.sparse_field`` and stay at their free-flight values; it
        is accepted by the same held-out criterion as a named effect, against ``current`` (the
        round's control when that did better). Added to the round's ranking; None where no field
        of few terms explains the flights.
        """
        base_law = _laws(current.effects, ctx)
        found = sparse_field(self.flight, base_law)
        if found is None:
            return None
        terms, origin, fit = found
        candidate = FieldCandidate(terms, origin, {label: fit.values[label]
                                                   for label in field_law(origin, terms).labels})
        base = self.flight.fit(base_law)
        ranked = Ranked(candidate, math.nan, dict(candidate.values),
                        flight=Flight(self.flight.explained(fit, base), fit.chi2,
                                      fit.chi2 + 2 * len(terms), dict(candidate.values),
                                      {label: fit.std[label] for label in candidate.values}))
        _LOG.info("free flight's force as a field: %s", "; ".join(candidate.describe()))
        self.try_candidate(ranked, current, ctx, limit)
        round_.ranking.append(ranked)
        return ranked

    def name_field(self, field: Ranked, round_: Round, ctx: Context) -> Model | None:
        """The accepted ``field``'s refit as the named effect whose law it is; None where it is none.

        The named effect whose law free flight favours (the lowest AIC there, every other law's
        more than ``TIE`` behind) is the field when its law, at the values nearest the field's,
        exerts the field's acceleration over the fitted frames' states within ``SAME_LAW``
        (``as_law``: a linear drag's velocity terms with one coefficient are linear drag). Its
        own refits failed the held-out criterion the field's refit of the same law passed: where
        refits of one model land that far apart (the second engine's linear drag at the full
        budget: its held refit x1.72, the field's x0.92) the field's stands for it, held at those
        values. A field that is a law free flight does not favour stays a field: over a short
        flight a constant and a drag fit alike, and the constant, the simplest term, is a wind.
        """
        laws = [(r.candidate, r.flight.aic) for r in round_.ranking
                if not isinstance(r.candidate, FieldCandidate) and r.flight is not None
                and math.isfinite(r.flight.aic) and r.flight.explained >= self.loop.min_explained]
        if not laws:
            return None
        laws.sort(key=lambda law: law[1])
        candidate = laws[0][0]
        if len(laws) > 1 and laws[1][1] - laws[0][1] <= TIE:
            return None
        values, misfit = as_law(field.candidate.law, field.candidate.values, candidate.force_law(ctx), self.flight)
        if misfit > SAME_LAW:
            return None
        held = HeldCandidate(candidate, values)
        at = ", ".join(f"{k} = {v:.4g}" for k, v in values.items())
        field.note += (f"; the field is {candidate.name}'s law ({at}, {misfit:.1%} apart over the fitted "
                       f"frames' states), the law free flight favours: named {candidate.name}")
        _LOG.info("the field is %s's law (%s, %.1f%% apart): named %s", candidate.name, at, 100 * misfit,
                  candidate.name)
        effects = field.refit.effects[:-1] + [(held, dict(values))]
        return replace(field.refit, effects=effects, scene=self.declared(effects, ctx))

    def choose_families(self) -> list[FamilyChoice]:
        """The family of every object the scene leaves open, chosen on the fitted frames.

        Chosen once (``identify.family``); every model of the loop then fits that family.
        """
        return select_families(self.given.frames[: self.window], self.given.lifted, self.scene,
                               self.identify, FitSettings.of(self.identify),
                               problem_options(self.identify, self.views), self.views,
                               self.gripper_poses, phase_progress(self.progress, "family"))

    def sensed(self, model: Model, candidate: Candidate, values: dict[str, float], ctx: Context) -> Observations | None:
        """The observations a sensor ``candidate`` at ``values`` makes on top of ``model``'s effects.

        None for a physical candidate, or where those values change nothing.
        """
        if not (candidate.sensor and candidate.reobserve(values, ctx)):
            return None
        return self.observations(model.effects + [(candidate, values)], ctx)

    def start(self, current: Model, candidate: Candidate, values: dict[str, float], ctx: Context) -> Observations:
        """The observations a refit of ``current`` with ``candidate`` at ``values`` starts on.

        A sensor effect's own (its first values are whole-frame shifts, which the refit keeps);
        for a physical effect, ``current``'s: its first values are a linear guess (a floor
        tilt's, from a residual measured on observations the declared floor cut, was twice the
        truth on the second engine's tilt), and observations remade at a wrong tilt mislead its
        refit, which instead continues on those its fitted values make (``fit``).
        """
        return self.observations(current.effects + ([(candidate, values)] if candidate.sensor else []), ctx)

    def try_candidate(self, ranked: Ranked, current: Model, ctx: Context, limit: float | None = None) -> None:
        """Refit with the candidate and judge it (see the module docstring, step 6).

        ``limit``: where free flight shows a force this candidate's law explains, the held-out
        error the refit may reach (``spread_limit`` of the material-only models), the evidence
        for the effect being free flight's.
        """
        candidate = ranked.candidate
        effects = [(c, values) for c, values in current.effects] + [(candidate, ranked.estimate)]
        try:
            ranked.refit = self.fit(effects, ctx, f"fit with {candidate.name}", candidate.name, ranked.velocity,
                                    start=self.start(current, candidate, ranked.estimate, ctx))
        except (SimulationError, ValueError) as error:
            ranked.note = f"refit failed: {error}"
            return
        baseline = max(current.held_out_error, 1e-12)
        ranked.ratio = ranked.refit.held_out_error / baseline
        evidenced = (limit is not None and ranked.flight is not None
                     and ranked.flight.explained >= self.loop.min_explained)
        if evidenced:
            ranked.threshold = limit / baseline
            ranked.accepted = bool(ranked.ratio <= ranked.threshold)
            ranked.note = (f"free flight shows it (explains {ranked.flight.explained:.2f} there); held-out "
                           f"error x{ranked.ratio:.2f} (accepts <= x{ranked.threshold:.2f}: no worse than "
                           "the material-only refits, within their spread)")
        else:
            ranked.threshold = self.loop.threshold(len(ranked.estimate))
            ranked.accepted = bool(ranked.ratio <= ranked.threshold)
            ranked.note = f"held-out error x{ranked.ratio:.2f} (accepts <= x{ranked.threshold:.2f})"
            most = self.loop.explains * self.loop.significance
            left = self.significance(ranked.refit) if ranked.accepted else 0.0
            if left > most:
                ranked.accepted = False
                ranked.note += (f"; but it leaves {left:.3g} noise units of residual (names <= {most:.3g}): "
                                "the model is wrong elsewhere, not credited to this effect")
        worse = self.flight_contradiction(current, ranked, ctx)
        if worse is not None:
            ranked.accepted = False
            ranked.note += (f"; free flight rules out its fitted value (chi-square +{worse:.0f}): "
                            "the refit bought its fit elsewhere")
        if (evidenced and not ranked.accepted and not isinstance(candidate, (HeldCandidate, FieldCandidate))
                and all(math.isfinite(s) for s in ranked.flight.std.values())):
            self.try_held(ranked, current, ctx)

    def try_held(self, ranked: Ranked, current: Model, ctx: Context) -> None:
        """Refit with the candidate held at free flight's values; it replaces the free one if accepted.

        Only for a candidate free flight shows, whose every knob free flight measures (each
        object it acts on flies free); judged by the same threshold as the free refit.
        """
        held = HeldCandidate(ranked.candidate, ranked.flight.values)
        effects = [(c, values) for c, values in current.effects] + [(held, held.values)]
        try:
            refit = self.fit(effects, ctx, f"fit with {held.name} held at free flight's values",
                             f"{held.name}-held", ranked.velocity, start=self.start(current, held, held.values, ctx))
        except (SimulationError, ValueError) as error:
            ranked.note += f"; held at free flight's values, its refit failed: {error}"
            return
        ratio = refit.held_out_error / max(current.held_out_error, 1e-12)
        accepted = bool(ratio <= ranked.threshold)
        ranked.note += (f"; held at free flight's values: held-out error x{ratio:.2f} "
                        f"({'accepted' if accepted else 'not accepted either'})")
        if accepted:
            ranked.candidate, ranked.refit, ranked.ratio, ranked.accepted = held, refit, ratio, True

    def flight_contradiction(self, current: Model, ranked: Ranked, ctx: Context) -> float | None:
        """How much worse (chi-square) free flight fits a refit's knob values than its best.

        Only where that is beyond chance (p < ``P_VALUE``); None where free flight allows them
        or cannot tell (no force law, no free flight).
        """
        law = ranked.candidate.force_law(ctx)
        if law is None or self.flight is None or not self.flight.segments or ranked.refit is None:
            return None
        joint = combine(_laws(current.effects, ctx), law)
        values = {k: v for _, fitted in ranked.refit.effects for k, v in fitted.items()}
        worse = self.flight.chi2_at(joint, values) - self.flight.fit(joint).chi2
        return worse if worse > chi2.ppf(1.0 - P_VALUE, len(joint.labels)) else None


def spread_limit(material_only: Sequence[float]) -> float:
    """The held-out error a refit whose effect free flight shows may reach.

    No worse than the material-only models' (the current model's and its control's), within
    their spread. Refits of one model land this far apart on the held-out frames (a few more iterations,
    warm-started, moved them from 4.4 to 8.7 mm on bags/thrown_ball), so a refit beyond the worst
    of them by less than that is not worse than a material-only refit.
    """
    worst, best = max(material_only), min(material_only)
    return worst + (worst - best)


def rollout(identifier: Identifier, observations: Observations) -> Prediction:
    """The identifier's simulation, as it stands, over every observed frame."""
    frames = observations.frames
    n = len(frames) - 1
    dt = identifier.problem.observations.frame_dt
    positions = identifier.sim.rollout(n)[:, 0].astype(np.float64)
    objects = identifier.problem.objects
    return Prediction(frames[0].stamp_ns, np.arange(n + 1) * dt, positions,
                      identifier.index, [o.id for o in objects], [o.name for o in objects],
                      observations.lifted.rgb)


def _laws(effects: Sequence[tuple[Candidate, dict[str, float]]], ctx: Context) -> ForceLaw | None:
    """The free-flight laws of a model's effects, as one law (None: none has one)."""
    return combine(*(c.force_law(ctx) for c, _ in effects))


def _weight(ranked: Ranked, flight_force: bool) -> float:
    """What orders a round's ranking: the free-flight share where a force acts there."""
    if flight_force:
        return ranked.flight.explained if ranked.flight is not None else -math.inf
    return ranked.explained


def _describe(ranked: Ranked) -> str:
    text = f"{ranked.candidate.name} {ranked.explained:.2f}"
    if ranked.flight is not None:
        text += f" (free flight {ranked.flight.explained:.2f})"
    return text + (" ruled out" if ranked.ruled_out else "")


def _material_estimates(estimates: Estimates) -> Estimates:
    """The estimates with effect parameters taken out of the objects (the scene carries them)."""
    keep = set(MATERIAL_PARAM_NAMES) | {OFFSET}
    objects = [replace(o, params={k: v for k, v in o.params.items() if k in keep},
                       std={k: v for k, v in o.std.items() if k in keep}) for o in estimates.objects]
    return replace(estimates, objects=objects)


def _start_at(problem: FitProblem, estimates: Estimates) -> None:
    """Set a problem's free object and ground parameters to where a fit ended."""
    by_name = {o.name: o for o in estimates.objects}
    for obj in problem.objects:
        previous = by_name.get(obj.name)
        if previous is None:
            continue
        for name, value in previous.params.items():
            if name in problem.free and name not in problem.fixed.get(obj.name, ()):
                obj.params[name] = value
    if "ground.friction" in estimates.scene and problem.sim_config.ground is not None:
        problem.sim_config.ground = copy.copy(problem.sim_config.ground)
        problem.sim_config.ground.friction = estimates.scene["ground.friction"]
