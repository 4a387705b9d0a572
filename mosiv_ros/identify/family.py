"""Choosing the material family of objects whose family the scene leaves open, by held-out error.

MOSIV and M-PhyGs take every object's material family as given. Here an object whose family the
scene declaration does not give (declared without ``family``, or not declared at all) gets one
of the candidate ``families`` (identify_node parameter), chosen by how well a fit of each
predicts frames it was not fitted on:

1. the fit window is split: its last ``HOLDOUT`` (at least ``MIN_HELD_OUT`` frames) is held out,
   the rest (at least ``MIN_FITTED`` frames) is fitted;
2. objects in id order, greedily (the other open objects at their current choice, the first of
   their candidates to begin with): for each candidate family of the object (those of
   ``families`` that use every parameter its declaration gives), the problem is fitted on the
   fitted frames (``identify.fit``, with the settings of the final fit), the fitted simulation
   is rolled over the whole window, and its score is the held-out error: the mean Chamfer
   distance (``mosiv_ros.metrics``) between each object's particles and its observed occupancy
   over the held-out frames. The lowest score wins;
3. a candidate whose fit or rollout fails (a diverging simulation, a parameter out of range)
   scores infinity, with the reason; the selection goes on.

An assignment of families already scored is not fitted again (the greedy order meets each
earlier winner again). With a checkpoint directory, each candidate fit checkpoints in a
subdirectory of its own (``family/<id>-<family>_...``) and every finished score is saved in
``SCORES_FILE``, so that an interrupted selection resumes without redoing finished candidates.
``identify.run.identify_objects`` then fits the chosen families on the whole window.

What it is for: the choice. What it is not for: the fit itself (``identify.fit``), the final
estimates (``identify.run``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from mosiv_ros.config import HOLDOUT, IdentifyConfig
from mosiv_ros.identify.estimates import Estimates
from mosiv_ros.identify.fit import FitSettings, Identifier
from mosiv_ros.identify.observations import Observations, View
from mosiv_ros.identify.problem import ProblemOptions, build_problem, object_name
from mosiv_ros.io.files import write_text
from mosiv_ros.io.scene import Scene, scene_to_yaml
from mosiv_ros.lifting.lift import LiftedParticles
from mosiv_ros.metrics import chamfer_distance
from mosiv_ros.recon.reconstruct import ObservedFrame
from mosiv_ros.sim.errors import SimulationError
from mosiv_ros.sim.materials import FAMILY_PARAMS
from mosiv_ros.simulation import declared_params

_LOG = logging.getLogger(__name__)

MIN_HELD_OUT = 2
MIN_FITTED = 3
SCORES_FILE = "family_scores.json"
"""Finished candidates' scores, in the checkpoint directory."""


@dataclass
class Trial:
    """One candidate family of one object: its held-out error (m; inf if it failed) and why."""

    family: str
    score: float
    reason: str = ""
    seconds: float = 0.0


@dataclass
class FamilyChoice:
    """The family chosen for an object the declaration leaves open, and the candidates tried.

    No trials: the object had one candidate only (nothing to choose).
    """

    id: int
    name: str
    family: str
    trials: list[Trial] = field(default_factory=list)

    @property
    def scores(self) -> dict[str, float]:
        """Held-out error (m) by candidate family."""
        return {t.family: t.score for t in self.trials}


def candidate_families(families: Sequence[str]) -> list[str]:
    """identify_node's ``families``, checked (ValueError naming the bad entry)."""
    known = ", ".join(FAMILY_PARAMS)
    if not families:
        raise ValueError(f"identify_node.families is empty: give at least one of {known}")
    for index, family in enumerate(families):
        if family not in FAMILY_PARAMS:
            raise ValueError(f"identify_node.families[{index}]: unknown material family {family!r} "
                             f"(known: {known})")
        if family in families[:index]:
            raise ValueError(f"identify_node.families[{index}]: {family!r} is listed twice")
    return list(families)


def with_family_scores(estimates: Estimates, choices: Sequence[FamilyChoice]) -> Estimates:
    """``estimates`` with each chosen object's candidate scores as its ``family_scores``."""
    scores = {c.id: c.scores for c in choices}
    for obj in estimates.objects:
        obj.family_scores = scores.get(obj.id, {})
    return estimates


def open_objects(lifted: LiftedParticles, scene: Scene,
                 families: Sequence[str]) -> dict[int, list[str]]:
    """The lifted objects whose family the scene leaves open, by id, with their candidates.

    An object's candidates are those of ``families`` that use every parameter its declaration
    gives; ValueError if none does.
    """
    declared = {o.id: o for o in scene.objects}
    candidates = {}
    for object_id in lifted.object_ids:
        item = declared.get(object_id)
        if item is not None and item.family is not None:
            continue
        known = set(declared_params(item))
        usable = [f for f in families if known <= set(FAMILY_PARAMS[f])]
        if not usable:
            raise ValueError(f"object {object_name(scene, object_id)!r} declares no family and "
                             f"parameters {sorted(known)} that no candidate family "
                             f"({', '.join(families)}) uses all of")
        candidates[object_id] = usable
    return candidates


def held_out_error(positions: np.ndarray, index: np.ndarray, observations: Observations,
                   fitted: int) -> float:
    """Mean Chamfer distance (m) of each object's particles to its observed points.

    Over frames ``fitted`` .. the last of ``positions`` (F, N, 3) and the objects seen there;
    inf when no object is seen there.
    """
    values = [chamfer_distance(positions[f][index == k], points)
              for f in range(fitted, len(positions))
              for k, points in enumerate(observations.points[f]) if len(points)]
    return float(np.mean(values)) if values else math.inf


def select_families(frames: Sequence[ObservedFrame], lifted: LiftedParticles, scene: Scene,
                    config: IdentifyConfig, settings: FitSettings, options: ProblemOptions,
                    views: Sequence[View] = (), gripper_poses: Sequence[tuple[int, np.ndarray]] = (),
                    progress: Callable[[dict], None] | None = None) -> list[FamilyChoice]:
    """The family of every object the scene leaves open, over the fit window ``frames``.

    See the module docstring. ``settings`` and ``options`` are those of the final fit;
    ``progress`` gets every candidate fit's iteration records, with a key ``candidate``
    ("<object>: <family>").
    """
    families = candidate_families(config.families)
    open_ = open_objects(lifted, scene, families)
    choice = {object_id: candidates[0] for object_id, candidates in open_.items()}
    names = {object_id: object_name(scene, object_id) for object_id in open_}
    contested = [object_id for object_id, candidates in open_.items() if len(candidates) > 1]
    if not contested:
        return [FamilyChoice(i, names[i], choice[i]) for i in open_]
    held_out = max(MIN_HELD_OUT, int(round(len(frames) * HOLDOUT)))
    fitted = len(frames) - held_out
    if fitted < MIN_FITTED:
        raise ValueError(
            f"choosing the family of {', '.join(names[i] for i in contested)} needs at least "
            f"{MIN_FITTED + MIN_HELD_OUT} frames in the fit window ({MIN_FITTED} fitted, "
            f"{MIN_HELD_OUT} held out), got {len(frames)}: declare the family or fit more frames")
    store = _Scores(config.checkpoint_dir, _signature(frames, lifted, scene, settings, options, fitted))
    fit = _CandidateFit(frames, lifted, scene, config, settings, options, views, gripper_poses, fitted)
    trials: dict[int, list[Trial]] = {}
    for object_id in contested:
        name = names[object_id]
        trials[object_id] = []
        for family in open_[object_id]:
            assignment = {**choice, object_id: family}
            key = "_".join(f"{i}-{f}" for i, f in sorted(assignment.items()))
            trial = store.get(key)
            if trial is None:
                _LOG.info("family of %s: fitting %s on %d frames, %d held out", name, family,
                          fitted, held_out)
                tagged = None if progress is None else (
                    lambda record, label=f"{name}: {family}": progress({**record, "candidate": label}))
                trial = fit(family, assignment, key, tagged)
                store.put(key, trial)
            else:  # scored before the interruption, or the assignment an earlier object chose
                _LOG.info("family of %s: %s scored before", name, family)
            trial = replace(trial, family=family)
            trials[object_id].append(trial)
            if math.isfinite(trial.score):
                _LOG.info("family of %s: %s held-out error %.2f mm", name, family, trial.score * 1e3)
            else:
                _LOG.warning("family of %s: %s failed: %s", name, family, trial.reason)
        best = min(trials[object_id], key=lambda t: t.score)  # ties: the earlier candidate
        if not math.isfinite(best.score):
            _LOG.warning("family of %s: every candidate failed; keeping %s", name, best.family)
        choice[object_id] = best.family
        _LOG.info("family of %s: %s (%s)", name, best.family, ", ".join(
            f"{t.family} {t.score * 1e3:.2f} mm" for t in trials[object_id]))
    return [FamilyChoice(i, names[i], choice[i], trials.get(i, [])) for i in open_]


@dataclass
class _CandidateFit:
    """Fits an assignment of families on the fitted frames and scores it on the held-out ones."""

    frames: Sequence[ObservedFrame]
    lifted: LiftedParticles
    scene: Scene
    config: IdentifyConfig
    settings: FitSettings
    options: ProblemOptions
    views: Sequence[View]
    gripper_poses: Sequence[tuple[int, np.ndarray]]
    fitted: int

    def __call__(self, family: str, assignment: dict[int, str], key: str,
                 progress: Callable[[dict], None] | None) -> Trial:
        tick = time.perf_counter()
        directory = self.config.checkpoint_dir
        checkpoint = str(Path(directory) / "family" / key) if directory else ""
        options = replace(self.options, families={**self.options.families, **assignment})
        try:
            # built over the whole window, so that one domain serves the fit and the rollout
            problem = build_problem(self.frames, self.lifted, self.scene, self.views,
                                    self.gripper_poses, options)
            whole = problem.observations
            problem.observations = whole.select(slice(0, self.fitted))
            problem.sim_config.device = self.config.device
            identifier = Identifier(problem, replace(self.settings, checkpoint_dir=checkpoint), progress)
            identifier.run()
            positions = identifier.sim.rollout(whole.n_frames - 1)[:, 0].astype(np.float64)
        except (SimulationError, ValueError, ArithmeticError) as error:
            return Trial(family, math.inf, f"{type(error).__name__}: {error}", time.perf_counter() - tick)
        score = held_out_error(positions, identifier.index, whole, self.fitted)
        reason = "" if math.isfinite(score) else "no object is observed on the held-out frames"
        return Trial(family, score, reason, time.perf_counter() - tick)


def _signature(frames: Sequence[ObservedFrame], lifted: LiftedParticles, scene: Scene,
               settings: FitSettings, options: ProblemOptions, fitted: int) -> str:
    """What the saved scores depend on: the window, the particles, the scene, the settings."""
    text = json.dumps({
        "stamps": [f.stamp_ns for f in frames], "fitted": fitted,
        "points": [[len(g.occupancy) for _, g in sorted(f.objects.items())] for f in frames],
        "particles": len(lifted.x), "x": round(float(lifted.x.sum()), 6),
        "tracks": [0 if f.tracks is None else len(f.tracks.track_id) for f in frames],
        "scene": scene_to_yaml(scene), "use_masks": options.use_masks, "use_tracks": options.use_tracks,
        "fit_density": options.fit_density,
        "settings": settings.result_settings(),
    })
    return hashlib.sha256(text.encode()).hexdigest()


class _Scores:
    """Finished candidates' trials by assignment key, saved in ``SCORES_FILE`` when a directory is set."""

    def __init__(self, directory: str, signature: str) -> None:
        self.path = Path(directory) / SCORES_FILE if directory else None
        self.signature = signature
        self.trials: dict[str, Trial] = {}
        if self.path is None or not self.path.is_file():
            return
        try:
            data = json.loads(self.path.read_text())
            if data.get("signature") != signature:
                _LOG.warning("%s belongs to another window or settings; scoring afresh", self.path)
                return
            self.trials = {key: Trial(t["family"], math.inf if t["score"] is None else float(t["score"]),
                                      t["reason"], float(t["seconds"]))
                           for key, t in data["trials"].items()}
        except (OSError, KeyError, TypeError, ValueError) as error:
            _LOG.warning("cannot read %s (%s); scoring afresh", self.path, error)

    def get(self, key: str) -> Trial | None:
        return self.trials.get(key)

    def put(self, key: str, trial: Trial) -> None:
        self.trials[key] = trial
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        trials = {k: {**asdict(t), "score": t.score if math.isfinite(t.score) else None}
                  for k, t in self.trials.items()}
        write_text(self.path, json.dumps({"signature": self.signature, "trials": trials}, indent=1))
