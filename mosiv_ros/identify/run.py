"""Stage 3 as one call: observed frames + lifted particles + scene -> estimates.

``identify_objects`` is what both ``mosiv run`` (``mosiv_ros.pipeline``) and ``identify_node``
do: choose the family of every object the scene leaves open among ``config.families``
(``identify.family``: by held-out error within the window), build the fit problem from the
frames (the first ``config.window`` of them, or all), fit, estimate the uncertainty, and turn
the result into ``Estimates`` (with the candidates' scores of a chosen family). A failed fit (a
simulation that keeps diverging, a problem that cannot be built) is reported as ERROR estimates
rather than raised, so that a node keeps running and a late subscriber learns what went wrong.

``fit_problem`` fits a problem already built (the loop closure, ``mosiv_ros.loop``, adds
effects to one before fitting it).

What it is for: the stage as a unit. What it is not for: its parts (``problem``, ``fit``,
``estimates``).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from mosiv_ros.config import IdentifyConfig
from mosiv_ros.identify import losses
from mosiv_ros.identify.estimates import ERROR, Estimates, ObjectEstimate, coordinate_std, estimates_of
from mosiv_ros.identify.family import (
    FamilyChoice,
    candidate_families,
    select_families,
    with_family_scores,
)
from mosiv_ros.identify.fit import FitProblem, FitResult, FitSettings, Identifier
from mosiv_ros.identify.observations import View
from mosiv_ros.identify.problem import ProblemError, ProblemOptions, build_problem, object_name
from mosiv_ros.io.scene import Scene
from mosiv_ros.lifting.lift import LiftedParticles
from mosiv_ros.progress import Progress
from mosiv_ros.recon.reconstruct import ObservedFrame
from mosiv_ros.sim.errors import SimulationError
from mosiv_ros.sim.runtime import build_aside, load_modules, resolve_device
from mosiv_ros.sim.simulator import kernel_modules

_LOG = logging.getLogger(__name__)


@dataclass
class Identification:
    """What stage 3 produced: the estimates, (when the fit ran) the fit itself, chosen families."""

    estimates: Estimates
    identifier: Identifier | None = None
    result: FitResult | None = None
    window: int = 0
    families: list[FamilyChoice] = field(default_factory=list)


def build_kernels_aside(device: str) -> threading.Thread:
    """Build and load the kernels an identification on ``device`` launches, in a daemon thread.

    On an empty kernel cache they take seconds to build (about 10 s on two CPU cores, 12 s on an
    H200, the first run after an install or an upgrade). Helper processes build the modules
    the thread has not reached, beside it (``sim.runtime.build_aside``); the thread ends when
    they have. Started as the recording begins to arrive (identify_node) or before the
    reconstruction (``mosiv run``), the build is done, or further on, when the fit needs it;
    the fit then waits for the build under way rather than starting another
    (``sim.runtime.load_modules``). A failure is logged: the fit meets the same error and
    reports it.
    """
    def build() -> None:
        try:
            where = resolve_device(device)
            modules = [*kernel_modules(where), losses.__name__]
            helpers = build_aside(where, modules)
            load_modules(where, modules)
            for helper in helpers:  # a helper that failed left its modules to this thread
                if helper.wait() != 0:
                    _LOG.debug("a helper process building kernels ended with code %d", helper.returncode)
        except Exception as error:  # noqa: BLE001 - the fit meets the same error and reports it
            _LOG.warning("building the kernels ahead of the fit failed (the fit will try again): %s", error)

    thread = threading.Thread(target=build, name="kernels", daemon=True)
    thread.start()
    return thread


def identify_objects(frames: Sequence[ObservedFrame], lifted: LiftedParticles, scene: Scene,
                     config: IdentifyConfig, views: Sequence[View] = (),
                     gripper_poses: Sequence[tuple[int, np.ndarray]] = (),
                     progress: Callable[[dict], None] | None = None) -> Identification:
    """Fit the objects of ``frames`` (from the lifted frame on); see the module docstring."""
    frames = sorted((f for f in frames if f.stamp_ns >= lifted.stamp_ns), key=lambda f: f.stamp_ns)
    window = min(config.window or len(frames), len(frames))
    choices: list[FamilyChoice] = []
    try:
        options = problem_options(config, views)
        choices = select_families(frames[:window], lifted, scene, config, FitSettings.of(config),
                                  options, views, gripper_poses, progress)
        options.families = {c.id: c.family for c in choices}
        problem = build_problem(frames[:window], lifted, scene, views, gripper_poses, options)
        identification = fit_problem(problem, config, progress, window)
        with_family_scores(identification.estimates, choices)
        identification.families = choices
        return identification
    except (ProblemError, SimulationError, ValueError) as error:
        _LOG.error("identification failed: %s", error)
        return Identification(failed_estimates(lifted, scene, str(error), frames, choices),
                              window=window, families=choices)


def problem_options(config: IdentifyConfig, views: Sequence[View]) -> ProblemOptions:
    """The problem options identify_node's parameters imply.

    Masks only for a silhouette loss, tracks only for a track loss; an object whose family the
    scene leaves open gets the first candidate family unless ``ProblemOptions.families`` says
    otherwise.
    """
    return ProblemOptions(default_family=candidate_families(config.families)[0],
                          use_masks=config.loss.silhouette_weight > 0 and bool(views),
                          use_tracks=config.loss.track_weight > 0,
                          fit_density=config.density_ratios)


def fit_problem(problem: FitProblem, config: IdentifyConfig,
                progress: Callable[[dict], None] | None = None, window: int = 0) -> Identification:
    """Fit a built problem (on ``config.device``) and estimate its uncertainty; errors raise."""
    problem.sim_config.device = config.device
    identifier = Identifier(problem, FitSettings.of(config), progress)
    result = identifier.run()
    std = None
    if config.uncertainty:
        rollouts = 1 + 2 * len(result.u)  # the end point and a step either way along each coordinate
        identifier.report({"phase": "uncertainty", "done": 0, "total": rollouts})
        std = coordinate_std(identifier, result)
        identifier.report({"phase": "uncertainty", "done": rollouts, "total": rollouts})
    return Identification(estimates_of(identifier, result, std), identifier, result, window)


def failed_estimates(lifted: LiftedParticles, scene: Scene, reason: str,
                     frames: Sequence[ObservedFrame],
                     choices: Sequence[FamilyChoice] = ()) -> Estimates:
    """ERROR estimates of every lifted object, saying why the fit failed.

    An object's family is the declared one, else the one ``choices`` chose, else "unknown".
    """
    family = {c.id: c.family for c in choices} | {o.id: o.family for o in scene.objects if o.family}
    objects = [ObjectEstimate(object_id, object_name(scene, object_id),
                              family.get(object_id, "unknown"), {}, level=ERROR,
                              message=f"fit failed: {reason}")
               for object_id in lifted.object_ids]
    start = frames[0].stamp_ns if frames else lifted.stamp_ns
    return with_family_scores(Estimates(objects, stamp_ns=start, frames=len(frames),
                                        scene_level=ERROR, scene_message=f"fit failed: {reason}"),
                              choices)


UNITS = {"search": "sample", "fit": "iteration", "uncertainty": "rollout"}
"""What a fit's progress records count, by phase (``Identifier.report``)."""


def phase_progress(progress: Progress | None, phase: str) -> Callable[[dict], None]:
    """A fit's progress-record callback that calls ``progress(label, done, total, unit)``.

    The Adam iterations count under ``phase``, the search and the uncertainty under
    "``phase``: search" and "``phase``: uncertainty"; a candidate family's fit (a record with
    ``candidate``) under "family <candidate>" in the same way, bars of their own.
    """

    def record_progress(record: dict) -> None:
        base = f"family {record['candidate']}" if "candidate" in record else phase
        label = base if record["phase"] == "fit" else f"{base}: {record['phase']}"
        if progress:
            progress(label, record["done"], record["total"], UNITS[record["phase"]])

    return record_progress
