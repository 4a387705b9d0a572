"""The report of a run: ``report.json``, ``report.md`` and plots, written into the output folder.

What it is for: turning the dictionary ``pipeline.run`` assembles (estimates, metrics, timing,
parameter errors against ground truth) into files a person reads: the estimates with their
standard deviations and status, the candidate families' held-out errors of an object whose
family was chosen (``identify.family``), the scores on the fitted and the held-out frames (and
the frames where an object is cut by an image border or has no geometry), and
two plots per object (observed vs predicted centroid path; Chamfer distance over time).
What it is not for: computing anything (``evaluate``, ``identify``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mosiv_ros.config import HOLDOUT
from mosiv_ros.evaluate.twin import PER_DENSITY, SCENE
from mosiv_ros.io.files import OutputDir, plain
from mosiv_ros.predict.twin import Prediction
from mosiv_ros.recon.reconstruct import ObservedFrame


def write_report(out: OutputDir, report: dict, prediction: Prediction, frames: Sequence[ObservedFrame],
                 fitted: int) -> list[Path]:
    """Write report.json, report.md and the plots (each whole: ``io.files``); return their paths."""
    paths = [out.write_text("report.json", json.dumps(plain(report, null_nonfinite=True), indent=1))]
    plots = _plots(out, report, prediction, frames, fitted)
    paths.append(out.write_text("report.md", _markdown(report, [p.name for p in plots])))
    return paths + plots


def _markdown(report: dict, plots: list[str]) -> str:
    est = report["estimates"]
    lines = [f"# mosiv run: {report['bag']}", "",
             f"{report['frames']} frames at {1 / report['frame_dt']:.1f} fps, the first "
             f"{report['fitted_frames']} fitted, the rest held out; {report['particles']} particles.",
             "", "## Estimates", "",
             "| object | family | parameter | estimate | std | truth | error | status |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    errors = report.get("parameter_errors", {})
    rows = [(obj["name"], obj["family"], obj["params"], obj["std"], f"{obj['level']} {obj['message']}")
            for obj in est["objects"]]
    rows.append((SCENE, "", est["scene"], est["scene_std"], f"{est['scene_level']} {est['scene_message']}"))
    for owner, family, params, stds, status in rows:
        for name, value in params.items():
            std = stds.get(name)
            err = errors.get(owner, {}).get(name, {})
            measure = next((f"{k} {v:+.3g}" for k, v in err.items()
                            if k in ("log10_ratio", "abs", "rel") and v is not None), "")
            if PER_DENSITY in err and err[PER_DENSITY] != err["log10_ratio"]:
                measure += f" (per density {err[PER_DENSITY]:+.3g})"
            std_text = "" if std is None else f"{std:.3g}"
            truth_text = f"{err['truth']:.4g}" if err else ""
            lines.append(f"| {owner} | {family} | {name} | {value:.4g} | {std_text} | {truth_text} | "
                         f"{measure} | {status} |")
    lines += _families(est["objects"], (report.get("fit") or {}).get("families", []))
    lines += ["", "## Scores", "",
              "| frames | CD (mm) | EMD (mm) | CD vs truth (mm) | IoU | PSNR (dB) | SSIM |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for part in ("observed", "future"):
        m = report["metrics"].get(part)
        if not m:
            continue
        cells = [_cell(m, "cd", 1e3), _cell(m, "emd", 1e3), _cell(m, "cd_truth", 1e3),
                 _cell(m, "iou"), _cell(m, "psnr"), _cell(m, "ssim")]
        lines.append(f"| {part} ({m['frames']}) | " + " | ".join(cells) + " |")
    tracks = report.get("tracks") or {}
    if tracks.get("attached"):
        lines += ["", f"Surface tracks: {tracks['attached']} attached to the twin's particles at the first "
                      f"frame ({tracks['dropped']} off them dropped); the twin's distance to them, median / RMS:"]
        lines += [f"{part} frames {tracks[part]['median'] * 1e3:.2f} / {tracks[part]['rms'] * 1e3:.2f} mm "
                  f"({tracks[part]['count']} track points)." for part in ("observed", "future") if part in tracks]
    for name, views in (report.get("views") or {}).items():
        lines += ["", f"Views: {name} is cut by an image border in {len(views['cut'])} of {report['frames']} "
                      f"frames ({frame_ranges(views['cut']) or 'none'}; {', '.join(views['cameras']) or 'no camera'}) "
                      f"and has no geometry in {len(views['missing'])} ({frame_ranges(views['missing']) or 'none'}): "
                      "its scores there cover only what the cameras show."]
    if report.get("truth_effects"):
        lines += ["", "Ground-truth effects: " + ", ".join(
            f"{e.get('type')} ({'declared' if e.get('declared') else 'undeclared'})"
            for e in report["truth_effects"])]
    timing = report["timing"]
    lines += ["", "## Time", "", ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in timing.items())]
    fit = report.get("fit") or {}
    if fit:
        lines += ["", f"Fit: {fit['iterations']} iterations, final loss {fit['loss']:.3g} m^2, "
                      f"{fit['failures']} diverged iterations undone."]
    lines += ["", "## Plots", ""] + [f"![{p}]({p})" for p in plots]
    return "\n".join(lines) + "\n"


def frame_ranges(frames: Sequence[int]) -> str:
    """Frame indices as ranges: [0, 1, 2, 5, 7, 8] -> '0-2, 5, 7-8'."""
    runs: list[list[int]] = []
    for k in sorted(frames):
        if runs and k == runs[-1][1] + 1:
            runs[-1][1] = k
        else:
            runs.append([k, k])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def _families(objects: list[dict], choices: list[dict]) -> list[str]:
    """The family selection table: each candidate's held-out error, the choice, why one failed."""
    chosen = [o for o in objects if o.get("family_scores")]
    if not chosen:
        return []
    reasons = {(c["id"], t["family"]): t["reason"] for c in choices for t in c["trials"]}
    lines = ["", "## Material family", "",
             "Not declared for the objects below: each candidate family was fitted on the fit "
             f"window less its last {HOLDOUT:.0%} and scored by its mean Chamfer distance to the "
             "observations there (held out); the lowest was chosen and fitted on the whole window.",
             "",
             "| object | candidate | held-out CD (mm) | |", "| --- | --- | --- | --- |"]
    for obj in chosen:
        for family, score in obj["family_scores"].items():
            if score is not None and math.isfinite(score):
                note, text = ("chosen" if family == obj["family"] else ""), f"{score * 1e3:.3g}"
            else:
                note, text = reasons.get((obj["id"], family), ""), "failed"
            lines.append(f"| {obj['name']} | {family} | {text} | {note} |")
    return lines


def _cell(metrics: dict, key: str, scale: float = 1.0) -> str:
    value = metrics.get(key)
    return "" if value is None else f"{value * scale:.3g}"


def _plots(out: OutputDir, report: dict, prediction: Prediction, frames: Sequence[ObservedFrame],
           fitted: int) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    paths = []
    t_obs = np.array([(f.stamp_ns - frames[0].stamp_ns) * 1e-9 for f in frames])
    window_end = t_obs[fitted - 1] if fitted else 0.0
    centroids = prediction.centroids()
    for k, (object_id, name) in enumerate(zip(prediction.object_ids, prediction.names, strict=True)):
        observed = np.array([f.objects[object_id].occupancy.mean(axis=0)
                             if object_id in f.objects and len(f.objects[object_id].occupancy)
                             else [np.nan] * 3 for f in frames])
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
        for axis, colour in zip(range(3), ("tab:red", "tab:green", "tab:blue"), strict=True):
            label = "xyz"[axis]
            axes[0].plot(prediction.times, centroids[:, k, axis], color=colour, label=f"{label} twin")
            axes[0].plot(t_obs, observed[:, axis], ".", color=colour, label=f"{label} observed")
        axes[0].axvline(window_end, color="grey", ls="--", lw=1)
        axes[0].set(xlabel="t (s)", ylabel="centroid (m)", title=f"{name}: path")
        axes[0].legend(fontsize=7, ncol=2)
        per_frame = report["per_frame"]
        t = [p["t"] for p in per_frame]
        cd = [p["cd"].get(object_id, np.nan) * 1e3 for p in per_frame]
        axes[1].plot(t, cd, label="CD vs reconstruction")
        truth = [p["cd_truth"].get(object_id, np.nan) * 1e3 for p in per_frame]
        if np.any(np.isfinite(truth)):
            axes[1].plot(t, truth, label="CD vs ground truth")
        axes[1].axvline(window_end, color="grey", ls="--", lw=1)
        axes[1].set(xlabel="t (s)", ylabel="mm", title=f"{name}: residual (dashed: end of fit)")
        axes[1].legend(fontsize=7)
        fig.tight_layout()
        paths.append(out.save_figure(f"{name}.png", fig))
        plt.close(fig)
    return paths
