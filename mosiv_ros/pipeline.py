"""The whole pipeline in-process: a recording in, a digital twin, estimates and a report out.

``run(bag, out, config)`` = ``mosiv run BAG --out DIR``: reconstruct every frame set (stage 1),
lift the first complete one (stage 2), fit the objects' parameters on the first frames (stage
3; the last ``holdout`` of the recording is kept out of the fit), estimate their uncertainty,
roll the identified twin over the whole recording and ``horizon`` seconds past it, score it
against the reconstruction (and the ground truth of a synthetic recording), and write
``estimates.yaml`` (a prediction_node params file), ``report.json``, ``report.md`` and plots.
``out`` is checked before any work and holds one run's files only (``io.files.OutputDir``).
The ROS nodes run the same stages on live topics; this is the same code without a ROS graph.

What it is for: the command line and tests. What it is not for: algorithms (each stage's
package has them).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from mosiv_ros.evaluate.twin import parameter_errors, score_frames, summarise, track_errors, view_coverage
from mosiv_ros.identify.estimates import ESTIMATES_FILE, Estimates
from mosiv_ros.identify.problem import views_of
from mosiv_ros.identify.run import build_kernels_aside, identify_objects, phase_progress
from mosiv_ros.io.files import OutputDir
from mosiv_ros.predict.twin import Twin
from mosiv_ros.prepare import Prepared, RunConfig, prepare
from mosiv_ros.progress import Progress
from mosiv_ros.report import write_report
from mosiv_ros.sim.errors import SimulationError
from mosiv_ros.synth.ground_truth import ground_truth_if_any

_LOG = logging.getLogger(__name__)


@dataclass
class RunResult:
    estimates: Estimates
    report: dict
    out: Path


def fit_window(frames: int, holdout: float) -> int:
    """How many of a recording's ``frames`` are fitted when the last ``holdout`` are held out (>= 2)."""
    return max(2, int(round(frames * (1 - holdout))))


def run(bag: str | Path, out: str | Path, config: RunConfig | None = None,
        progress: Progress | None = None) -> RunResult:
    """Run every stage on a recording (the module docstring); ``progress``: ``mosiv_ros.progress``."""
    config = config or RunConfig()
    directory = OutputDir(out, f"mosiv run {bag}")  # before any work: a bad place fails now
    build_kernels_aside(config.identify.device)  # while the recording is reconstructed
    return run_prepared(prepare(bag, config, progress), directory, config, progress)


def run_prepared(prepared: Prepared, out: OutputDir, config: RunConfig,
                 progress: Progress | None = None) -> RunResult:
    """``run`` from the fit on: identification, twin, scores and report of a prepared recording."""
    identify = config.identify
    if not identify.window:
        window = fit_window(len(prepared.frames), config.holdout)
        identify = replace(identify, window=window)
    _LOG.info("stage 3, identification: the first %d of %d frames", identify.window,
              len(prepared.frames))
    tick = time.perf_counter()
    identification = identify_objects(prepared.frames, prepared.lifted, prepared.recording.scene,
                                      identify, views_of(prepared.recording),
                                      prepared.recording.gripper_poses,
                                      phase_progress(progress, "identify"))
    prepared.timing["identify_s"] = time.perf_counter() - tick
    out.write_text(ESTIMATES_FILE, identification.estimates.file_text(ESTIMATES_FILE))
    if identification.result is None:
        raise SimulationError(f"identification failed: {identification.estimates.scene_message}")
    result = identification.result
    fit = {"loss": result.loss, "iterations": len(result.history), "failures": result.failures,
           "search_s": result.search_s, "race": result.race,
           "history": [{k: v for k, v in h.items() if k != "values"} for h in result.history],
           "families": [asdict(choice) for choice in identification.families]}
    return evaluate(prepared, identification.estimates, identification.window, out, config, fit)


def evaluate(prepared: Prepared, estimates: Estimates, window: int, out: OutputDir,
             config: RunConfig, fit: dict | None = None) -> RunResult:
    """Roll the twin of ``estimates`` over the recording and past it, score it, write the report."""
    timing = dict(prepared.timing)
    tick = time.perf_counter()
    scene = prepared.recording.scene
    twin = Twin(prepared.lifted, estimates, scene, device=config.prediction.device,
                gripper_poses=prepared.recording.gripper_poses)
    seconds = (len(prepared.frames) - 1) * estimates.frame_dt + config.prediction.horizon
    _LOG.info("prediction: the twin over the recording and %.1f s past it", config.prediction.horizon)
    prediction = twin.predict(seconds)
    timing["predict_s"] = time.perf_counter() - tick
    truth, truth_particles = ground_truth_if_any(prepared.bag)
    _LOG.info("scoring the twin%s", " (re-rendering every view)" if config.render else "")
    tick = time.perf_counter()
    scores = score_frames(prediction, prepared.frames, prepared.recording, window,
                          prepared.lifted.lattice_volume ** (1 / 3), truth_particles, config.render)
    timing["evaluate_s"] = time.perf_counter() - tick
    report = {
        "bag": str(prepared.bag), "frames": len(prepared.frames), "fitted_frames": window,
        "frame_dt": estimates.frame_dt, "particles": int(len(prepared.lifted.x)),
        "estimates": estimates.to_dict(), "metrics": summarise(scores),
        "per_frame": [s.__dict__ for s in scores], "timing": timing, "fit": fit or {},
        "tracks": track_errors(prediction, prepared.tracks, window, prepared.lifted.lattice_volume ** (1 / 3)),
        "views": view_coverage(prepared.frames, [(o.id, o.name) for o in estimates.objects]),
    }
    if truth is not None:
        report["parameter_errors"] = parameter_errors(estimates, truth)
        report["truth_effects"] = truth.get("effects", [])
    write_report(out, report, prediction, prepared.frames, window)
    return RunResult(estimates, report, out.path)
