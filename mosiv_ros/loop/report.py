"""``mosiv close-loop BAG --out DIR``: the loop on a recording, and its report.

``close_loop(bag, out, config, loop)`` runs stages 1-2 (``prepare.prepare``), the loop
(``closure.LoopClosure``) and writes into ``out``:

- ``close_loop.json``: verdict, the families chosen for objects the scene leaves open, the
  free-flight evidence (segments, noise, the force shown and its p-value), every round's
  control refit and candidate ranking (explained fraction of the residual and of the free-flight
  force, first knob estimates, refit held-out error and AIC, ratio against the acceptance
  threshold, accepted or not, why not), the accepted effects with their
  fitted values, the model before and after (estimates, centroid errors on the fitted and the
  held-out frames, CD/EMD (and IoU, PSNR, SSIM unless ``render`` is off) from
  ``evaluate.twin``, parameter errors against ``ground_truth.yaml`` for a synthetic recording)
  and the residual analysis of both, and for a synthetic recording the reconstruction's own
  centroid error (the recorder's particles as the prediction: the floor of any model's);
- ``close_loop.md``: the same for a person to read;
- plots per object: ``<object>_residual.png`` (centroid and shape residual over time, before
  and after), ``<object>_paths.png`` (observed vs predicted centroid paths, before and
  after) and, for an object that flies free, ``<object>_free_flight.png`` (its observed
  acceleration there against the declared gravity), and ``ranking.png`` (the candidates of
  every round);
- ``closed_scene.yaml`` (the scene declaration with the accepted effects: a ``scene`` parameter
  for prediction_node) and ``estimates.yaml`` (the closed model's estimates).

``out`` is an ``io.files.OutputDir``: checked before any work, each file written whole, one
run's files only.

What it is for: the command and identify_node's option. What it is not for: the loop's logic.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from mosiv_ros.evaluate.twin import parameter_errors, score_frames, summarise
from mosiv_ros.identify.estimates import ESTIMATES_FILE
from mosiv_ros.identify.problem import views_of
from mosiv_ros.identify.run import build_kernels_aside
from mosiv_ros.io.files import OutputDir, plain
from mosiv_ros.io.scene import scene_to_yaml
from mosiv_ros.loop.closure import LoopClosure, LoopConfig, LoopResult, Model
from mosiv_ros.loop.freeflight import MIN_FORCE, MIN_FRAMES, P_VALUE
from mosiv_ros.loop.library import FieldCandidate, FloorTiltCandidate, tilt_degrees
from mosiv_ros.loop.observations import Reobserver
from mosiv_ros.loop.residual import analyse
from mosiv_ros.predict.twin import Prediction
from mosiv_ros.prepare import Prepared, RunConfig, prepare
from mosiv_ros.progress import Progress
from mosiv_ros.synth.ground_truth import GroundTruthParticles, ground_truth_if_any

_LOG = logging.getLogger(__name__)


def close_loop(bag: str | Path, out: str | Path, config: RunConfig | None = None,
               loop: LoopConfig | None = None,
               progress: Progress | None = None) -> dict:
    """Run the loop closure on a recording and write its report into ``out``; return the JSON.

    Its fits checkpoint under ``identify.checkpoint_dir``, by default ``out/checkpoints``: the
    same command run again resumes an interrupted loop.
    """
    directory = OutputDir(out, f"mosiv close-loop {bag}")  # before any work: a bad place fails now
    config = config or RunConfig()
    build_kernels_aside(config.identify.device)  # while the recording is reconstructed
    return close_loop_prepared(prepare(bag, config, progress), directory, config, loop, progress)


def close_loop_prepared(prepared: Prepared, out: OutputDir, config: RunConfig,
                        loop: LoopConfig | None = None, progress: Progress | None = None) -> dict:
    """``close_loop`` on a recording whose stages 1-2 are done (``mosiv batch`` shares them)."""
    loop = loop or LoopConfig(holdout=config.holdout)
    identify = config.identify
    if not identify.checkpoint_dir:
        identify = replace(identify, checkpoint_dir=str(out.path / "checkpoints"))
    closure = LoopClosure(prepared.frames, prepared.lifted, prepared.recording.scene,
                          identify, loop, views_of(prepared.recording),
                          prepared.recording.gripper_poses, progress=progress,
                          reobserver=Reobserver(prepared.recording, config))
    result = closure.run()
    return write_loop_report(out, result, prepared, config.render)


def write_loop_report(out: OutputDir, result: LoopResult, prepared: Prepared | None = None,
                      render: bool = False) -> dict:
    """Write the files of the module docstring; ``prepared`` adds CD/EMD and truth scores."""
    truth, truth_particles = ground_truth_if_any(prepared.bag) if prepared else (None, None)
    report = {
        "verdict": result.verdict, "frames": len(result.before.analysis.times),
        "fitted_frames": result.window, "loop_seconds": result.seconds,
        "criterion": (f"accept an effect of p knobs when held-out centroid error new/current <= "
                      f"{result.config.margin} * exp(-{result.config.penalty} p)"),
        "config": dict(result.config.__dict__),
        "families": [asdict(choice) for choice in result.families],
        "accepted": [_effect(c, values) for c, values in result.after.effects],
        "free_flight": _flight(result),
        "rounds": [{"significance": r.significance, "accepted": r.accepted,
                    "flight_force": r.flight_force,
                    "control": None if r.control is None else {
                        "centroid_error": r.control.analysis.errors(), "information": r.control.information},
                    "ranking": [_ranked(x) for x in r.ranking]} for r in result.rounds],
        "before": _model(result.before, prepared, truth, truth_particles, render),
        "after": _model(result.after, prepared, truth, truth_particles, render),
    }
    if truth_particles is not None:
        report["reconstruction_floor"] = _floor(result, truth_particles)
    if truth is not None:
        report["truth_effects"] = truth.get("effects", [])
    out.write_text("closed_scene.yaml", scene_to_yaml(result.after.scene))
    out.write_text(ESTIMATES_FILE, result.after.estimates.file_text(ESTIMATES_FILE))
    plots = _plots(out, result)
    out.write_text("close_loop.json", json.dumps(plain(report, null_nonfinite=True), indent=1))
    out.write_text("close_loop.md", _markdown(report, [p.name for p in plots]))
    return report


def _effect(candidate, values: dict[str, float]) -> dict:
    entry = {"name": candidate.name, "doc": candidate.doc, "values": values}
    if isinstance(candidate, FloorTiltCandidate):
        entry["tilt_deg"] = tilt_degrees(values)
    if isinstance(candidate, FieldCandidate):
        entry["terms"] = candidate.describe()
        entry["origin"] = candidate.origin.tolist()
    return entry


def _ranked(ranked) -> dict:
    return {"name": ranked.candidate.name, "signature": ranked.candidate.signature,
            "explained": ranked.explained, "estimate": ranked.estimate,
            "free_flight": None if ranked.flight is None else asdict(ranked.flight),
            "ruled_out": ranked.ruled_out,
            "refit_held_out_error": ranked.refit.held_out_error if ranked.refit else None,
            "refit_values": dict(ranked.refit.effects[-1][1]) if ranked.refit else None,
            "refit_information": ranked.refit.information if ranked.refit else None,
            "ratio": ranked.ratio, "threshold": ranked.threshold, "accepted": ranked.accepted,
            "note": ranked.note}


def _flight(result: LoopResult) -> dict | None:
    flight = result.flight
    if flight is None:
        return None
    names = result.before.analysis.names
    entry = {"segments": [{"object": names[s.object], "frames": [s.start, s.stop - 1]} for s in flight.segments],
             "reach_m": flight.reach, "frames": flight.frames}
    if flight.null is not None:
        entry.update({"noise_m": {names[k]: float(v) for k, v in enumerate(flight.noise) if np.isfinite(v)},
                      "chi2_null": flight.chi2_null, "chi2_smooth": flight.chi2_flexible,
                      "p_value": flight.p_value(flight.null), "force": flight.force(flight.null),
                      "significant": flight.significant})
    return entry


def _floor(result: LoopResult, truth: GroundTruthParticles) -> dict | None:
    """The observations' own centroid error: the recorder's particles as the prediction.

    No model predicts the reconstructed centroids closer than the truth does, other than by
    fitting the reconstruction's bias: what is left of a model's held-out error above this is
    the model's. None where the truth lacks a frame of the observations.
    """
    model = result.before
    frames = model.observations.frames
    rows = [np.flatnonzero(truth.stamps_ns == f.stamp_ns) for f in frames]
    if any(not len(r) for r in rows):
        return None
    ids = model.prediction.object_ids
    mine = np.isin(truth.object_id, ids)
    index = np.array([ids.index(int(i)) for i in truth.object_id[mine]])
    positions = truth.positions[[r[0] for r in rows]][:, mine].astype(np.float64)
    times = (np.array([f.stamp_ns for f in frames]) - frames[0].stamp_ns) * 1e-9
    prediction = Prediction(frames[0].stamp_ns, times, positions, index, list(ids), list(model.prediction.names))
    return analyse(frames, prediction, model.analysis.fitted, None).errors()


def _model(model: Model, prepared: Prepared | None, truth, truth_particles, render: bool) -> dict:
    entry = {"effects": [_effect(c, v) for c, v in model.effects],
             "centroid_error": model.analysis.errors(), "fit_seconds": model.seconds,
             "information": model.information,
             "estimates": model.estimates.to_dict(), "residual": model.analysis.to_dict()}
    if prepared is not None:
        observations = model.observations
        spacing = observations.lifted.lattice_volume ** (1 / 3)
        if truth_particles is not None:  # from the model's first frame on
            first = int(np.searchsorted(truth_particles.stamps_ns, observations.frames[0].stamp_ns))
            truth_particles = replace(truth_particles, positions=truth_particles.positions[first:],
                                      stamps_ns=truth_particles.stamps_ns[first:],
                                      times=truth_particles.times[first:])
        scores = score_frames(model.prediction, observations.frames, prepared.recording,
                              model.analysis.fitted, spacing, truth_particles, render)
        entry["metrics"] = summarise(scores)
    if truth is not None:
        entry["parameter_errors"] = parameter_errors(model.estimates, truth)
    return entry


def _markdown(report: dict, plots: list[str]) -> str:
    before, after = report["before"], report["after"]
    lines = [f"# Loop closure: {report['verdict']}", "",
             f"{report['frames']} frames, the first {report['fitted_frames']} fitted, the rest held "
             f"out. Criterion: {report['criterion']}.", "", "## Effects accepted", ""]
    if report["accepted"]:
        for effect in report["accepted"]:
            values = ", ".join(f"{k} = {v:.4g}" for k, v in effect["values"].items())
            tilt = f" (tilt {effect['tilt_deg']:.2f} deg)" if "tilt_deg" in effect else ""
            if "terms" in effect:  # a field, not a named effect
                lines.append(f"- **unmodelled external force** (not a named physical effect: a smooth field "
                             f"fitted where the objects fly free, positions about {_point(effect['origin'])}): "
                             + "; ".join(effect["terms"]))
                continue
            lines.append(f"- **{effect['name']}** ({effect['doc']}): {values}{tilt}")
    else:
        lines.append("- none")
    if report.get("truth_effects"):
        lines += ["", "Ground truth: " + ", ".join(
            f"{e['type']} ({'declared' if e['declared'] else 'undeclared'}) {e['params']}"
            for e in report["truth_effects"])]
    flight = report.get("free_flight")
    if flight:
        lines += ["", "## Free flight", ""]
        if "p_value" not in flight:
            lines.append(f"No object flies free for {MIN_FRAMES} frames (clear of everything by "
                         f"{flight['reach_m'] * 1e3:.0f} mm): no free-flight evidence.")
        else:
            segments = ", ".join(f"{s['object']} frames {s['frames'][0]}-{s['frames'][1]}"
                                 for s in flight["segments"])
            noise = ", ".join(f"{k} {v * 1e3:.2f} mm" for k, v in flight["noise_m"].items())
            lines.append(f"Free (clear of everything by {flight['reach_m'] * 1e3:.0f} mm): {segments}; "
                         f"centroid noise {noise}. External force beyond the declared gravity: "
                         f"{flight['force']:.2f} m/s^2, p = {flight['p_value']:.2g}: "
                         f"{'a force acts' if flight['significant'] else 'none shown'} "
                         f"(acts when p < {P_VALUE:g} and at least {MIN_FORCE} m/s^2).")
    lines += ["", "## Error before and after", "",
              "| model | centroid RMS fitted (mm) | centroid RMS held-out (mm) | CD observed (mm) | "
              "CD future (mm) | AIC | BIC |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for label, model in (("before", before), ("after", after)):
        metrics = model.get("metrics", {})
        cd = [mm(metrics.get(part, {}).get("cd")) for part in ("observed", "future")]
        info = model.get("information", {})
        lines.append(f"| {label} | {mm(model['centroid_error']['fitted'])} | "
                     f"{mm(model['centroid_error']['held_out'])} | {cd[0]} | {cd[1]} | "
                     f"{_num(info.get('aic'))} | {_num(info.get('bic'))} |")
    floor = report.get("reconstruction_floor")
    if floor:
        lines.append(f"| the truth (the recorder's particles) | {mm(floor['fitted'])} | "
                     f"{mm(floor['held_out'])} | | | | |")
        lines += ["", "The truth's row is the reconstruction's own centroid error: what a model leaves "
                  "above it is the model's."]
    if "parameter_errors" in before:
        lines += ["", "## Parameters against the truth", "",
                  "| object | parameter | truth | before | after |", "| --- | --- | --- | --- | --- |"]
        for name, params in before["parameter_errors"].items():
            for param, err in params.items():
                new = after["parameter_errors"].get(name, {}).get(param, {})
                lines.append(f"| {name} | {param} | {err['truth']:.4g} | {err['estimate']:.4g} | "
                             f"{new.get('estimate', float('nan')):.4g} |")
    for i, round_ in enumerate(report["rounds"], 1):
        lines += ["", f"## Round {i}: residual {round_['significance']:.3g} (noise units; "
                  f"threshold {report['config']['significance']})", ""]
        if not round_["ranking"]:
            lines.append("No ranking: the residual is at the noise level.")
            continue
        if round_["flight_force"]:
            lines.append("A force acts in free flight that the model lacks: only an effect that exerts "
                         "one there can explain it.")
        control = round_.get("control")
        if control is not None:
            lines.append(f"Control (the model refitted with a candidate's budget, no new effect): held-out "
                         f"{mm(control['centroid_error']['held_out'])} mm, AIC "
                         f"{_num(control['information'].get('aic'))}.")
        lines += ["", "| candidate | explained | free flight | first estimate | refit held-out (mm) | "
                  "refit AIC | ratio | accepted | note |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in round_["ranking"]:
            estimate = ", ".join(f"{k} {v:.3g}" for k, v in r["estimate"].items())
            refit = mm(r["refit_held_out_error"]) if r["refit_held_out_error"] is not None else ""
            ratio = f"x{r['ratio']:.2f} (<= x{r['threshold']:.2f})" if r["refit_held_out_error"] is not None else ""
            flown = "" if r["free_flight"] is None else f"{r['free_flight']['explained']:.2f}"
            aic = _num((r["refit_information"] or {}).get("aic"))
            lines.append(f"| {r['name']} | {r['explained']:.2f} | {flown} | {estimate} | {refit} | {aic} | "
                         f"{ratio} | {'yes' if r['accepted'] else 'no'} | {r['note']} |")
    lines += ["", "## Residual (before)", "", "| object | growth (mm/s) | oscillation | contact jump | "
              "corr. speed | corr. speed^2 | corr. height | corr. contact |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for obj in before["residual"]["objects"]:
        ts, cr = obj["time_structure"], obj["correlations"]
        lines.append(f"| {obj['name']} | {_num(ts['growth_m_per_s'], 1e3)} | {_num(ts['oscillation'])} | "
                     f"{_num(ts['contact_jump'])} | {_num(cr['speed'])} | {_num(cr['speed_squared'])} | "
                     f"{_num(cr['height'])} | {_num(cr['contact'])} |")
    lines += ["", f"Loop time {report['loop_seconds']:.0f} s.", "", "## Plots", ""]
    lines += [f"![{p}]({p})" for p in plots]
    return "\n".join(lines) + "\n"


def _point(x) -> str:
    return "(" + ", ".join(f"{v:.3f}" for v in x) + ") m"


def mm(metres: float | None, digits: int = 2) -> str:
    """A length in metres as millimetres for a table; empty where there is none (None, NaN)."""
    return _num(metres, 1e3, digits)


def _num(value, scale: float = 1.0, digits: int = 2) -> str:
    return "" if value is None or not np.isfinite(value) else f"{value * scale:.{digits}f}"


def _plots(out: OutputDir, result: LoopResult) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    paths = []
    before, after = result.before.analysis, result.after.analysis
    t = before.times
    # a model on remade observations (a sensor effect) may start a frame later
    t_after = after.times + (result.after.prediction.start_ns - result.before.prediction.start_ns) * 1e-9
    end = t[result.window - 1]
    for k, name in enumerate(before.names):
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
        for analysis, times, style, label in ((before, t, "--", "before"), (after, t_after, "-", "after")):
            axes[0].plot(times, np.linalg.norm(analysis.centroid[:, k], axis=-1) * 1e3, style, label=label)
            axes[1].plot(times, analysis.shape[:, k] * 1e3, style, label=label)
        axes[0].set(xlabel="t (s)", ylabel="mm", title=f"{name}: centroid residual")
        axes[1].set(xlabel="t (s)", ylabel="mm", title=f"{name}: radius of gyration residual")
        for axis in axes:
            axis.axvline(end, color="grey", ls=":", lw=1)
            axis.legend(fontsize=7)
        fig.tight_layout()
        paths.append(out.save_figure(f"{name}_residual.png", fig))
        plt.close(fig)
        fig, axes = plt.subplots(1, 3, figsize=(12, 3.5))
        for axis_index, axis in enumerate(axes):
            axis.plot(t, before.observed[:, k, axis_index], "k.", label="observed")
            axis.plot(t, before.predicted[:, k, axis_index], "--", label="before")
            axis.plot(t_after, after.predicted[:, k, axis_index], "-", label="after")
            axis.axvline(end, color="grey", ls=":", lw=1)
            axis.set(xlabel="t (s)", ylabel="m", title=f"{name}: {'xyz'[axis_index]}")
            axis.legend(fontsize=7)
        fig.tight_layout()
        paths.append(out.save_figure(f"{name}_paths.png", fig))
        plt.close(fig)
    flight = result.flight
    for k, name in enumerate(before.names):
        if flight is None or not any(s.object == k for s in flight.segments):
            continue
        a, sd = flight.acceleration(k)
        fig, axes = plt.subplots(1, 3, figsize=(12, 3.5))
        for axis_index, axis in enumerate(axes):
            axis.errorbar(flight.times, a[:, axis_index], yerr=2 * sd[:, axis_index], fmt="k.",
                          capsize=2, label="observed (2 sd)")
            axis.axhline(flight.gravity[axis_index], color="tab:blue", ls="--", label="declared gravity")
            axis.set(xlabel="t (s)", ylabel="m/s^2", title=f"{name}: free-flight a_{'xyz'[axis_index]}")
            axis.legend(fontsize=7)
        fig.tight_layout()
        paths.append(out.save_figure(f"{name}_free_flight.png", fig))
        plt.close(fig)
    ranked = [(i, r) for i, round_ in enumerate(result.rounds, 1) for r in round_.ranking]
    if ranked:
        fig, axis = plt.subplots(figsize=(7, 0.35 * len(ranked) + 1.2))
        labels = [f"round {i}: {r.candidate.name}" for i, r in ranked]
        colours = ["tab:green" if r.accepted else "tab:grey" for _, r in ranked]
        axis.barh(labels[::-1], [max(r.explained, 0.0) for _, r in ranked][::-1], color=colours[::-1])
        axis.axvline(result.config.min_explained, color="k", ls=":", lw=1)
        axis.set(xlabel="explained fraction of the residual (green: accepted)", xlim=(0, 1))
        fig.tight_layout()
        paths.append(out.save_figure("ranking.png", fig))
        plt.close(fig)
    return paths
