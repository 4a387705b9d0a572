"""Identification of the sample recordings end to end: wall time, parameter errors, scores.

    python benchmarks/identify_samples.py bags/elastic_on_plastic --device cuda:0 \\
        --params-file config/mosiv.yaml --out out/identify_cuda.json

Runs ``mosiv_ros.pipeline.run`` (the same as ``mosiv run``: reconstruction, lifting, fit on the
first 70 % of the frames, uncertainty, twin, scores) on each bag and writes, per bag, the time of
every stage, when each progress phase (reconstruction, search, Adam, uncertainty, ...) was
reported first and last (``progress.PhaseSpans``, seconds from the bag's start), the fit's
iterations (the search's wall time, the race of its closest ends through
the first curriculum stage, the mean wall time of an iteration, split into simulation forward,
loss and backward, and per stage the iterations' summed times and the range of their substeps
a frame) and how many diverged, every estimated parameter against
``ground_truth.yaml`` (log10 ratio for moduli, absolute error for nu, relative error otherwise)
and the CD, EMD, IoU, PSNR, SSIM and the surface track error on the fitted and the held-out
frames. A params file with ``loss: {track_weight: 0.0}`` fits without
the track loss (tracks off against on, side by side). ``--ablation`` adds a second fit with the
scene-level (union) losses instead of the per-object ones.

Two switches fit from a better model than the recording gives, to tell what the estimated
geometry and the assumed densities cost the fit (as ``objective_scan.py`` does for its loss):
``--true-particles`` (all objects, or ``--true-particles cube``) starts those objects from the
recorder's own particles at the lifted frame, and ``--density truth`` (or ``--density
sand=1600``) declares objects' densities at their true (or given) values. ``--true-effects``
declares the effects the recording leaves undeclared (thrown_ball's air drag, cube_on_slab's
wind) at their true values: what the fit costs, and finds, when the model lacks nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
from objective_scan import asked_densities, declare_densities, declare_true_effects, with_true_particles_of

from mosiv_ros.cli import run_config
from mosiv_ros.config import updated
from mosiv_ros.identify.run import build_kernels_aside
from mosiv_ros.io.files import OutputDir, plain
from mosiv_ros.pipeline import run_prepared
from mosiv_ros.prepare import RunConfig, prepare
from mosiv_ros.progress import PhaseSpans, Progress
from mosiv_ros.synth.ground_truth import read_ground_truth


def prepared_with(bag: Path, config: RunConfig, true_particles: str, density: list[str],
                  true_effects: bool = False, progress: Progress | None = None):
    """``prepare(bag)``, with the recorder's particles, declared densities and effects where asked."""
    prepared = prepare(bag, config, progress)
    if not true_particles and not density and not true_effects:
        return prepared
    truth = read_ground_truth(bag)
    objects = {o["name"]: o for o in truth["objects"]}
    if true_particles:
        prepared.lifted = with_true_particles_of(prepared.lifted, bag, true_particles, objects)
    declare_densities(asked_densities(density, objects), prepared.recording.scene.objects)
    if true_effects:
        declare_true_effects(prepared.recording.scene, truth)
    return prepared


def one(bag: Path, config: RunConfig, out: Path, true_particles: str = "",
        density: list[str] | None = None, true_effects: bool = False) -> dict:
    start = time.perf_counter()
    phases = PhaseSpans()
    directory = OutputDir(out, f"benchmarks/identify_samples.py {bag}")
    build_kernels_aside(config.identify.device)  # as mosiv run does
    prepared = prepared_with(bag, config, true_particles, density or [], true_effects, phases)
    result = run_prepared(prepared, directory, config, phases)
    report = result.report
    fit = report["fit"]
    history = fit.get("history", [])
    mean = {f"iteration_{key}": float(np.mean([h[key] for h in history])) if history else None
            for key in ("seconds", "forward_s", "loss_s", "backward_s")}
    stages = []  # the race's stage, and each stage after it: where an iteration's time goes
    for stage in sorted({h["stage"] for h in history}):
        records = [h for h in history if h["stage"] == stage]
        substeps = [h["substeps"] for h in records if "substeps" in h]
        stages.append({"stage": stage, "window": records[0]["window"], "iterations": len(records),
                       **{key: float(sum(h[key] for h in records)) for key in ("seconds", "forward_s", "backward_s")},
                       "substeps": [min(substeps), max(substeps)] if substeps else None})
    return {"bag": str(bag), "wall_s": time.perf_counter() - start, "timing": report["timing"],
            "phases": phases.spans(),
            "fit_iterations": fit.get("iterations"), "fit_failures": fit.get("failures"),
            "search_s": fit.get("search_s"), "race": fit.get("race"), **mean, "stages": stages,
            "particles": report["particles"],
            "frames": report["frames"], "fitted_frames": report["fitted_frames"],
            "estimates": report["estimates"]["objects"], "scene": report["estimates"]["scene"],
            "parameter_errors": report.get("parameter_errors", {}), "metrics": report["metrics"],
            "tracks": report["tracks"]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bags", nargs="+", type=Path)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--params-file", type=Path, default=None)
    parser.add_argument("--ablation", action="store_true", help="also fit with scene-level losses")
    parser.add_argument("--true-particles", nargs="?", const="all", default="",
                        help="'all' or comma-separated object names")
    parser.add_argument("--density", action="append", default=[], help="'truth' or object=kg/m^3")
    parser.add_argument("--true-effects", action="store_true",
                        help="declare the recording's undeclared effects at their true values")
    parser.add_argument("--out", type=Path, default=Path("out/identify_samples.json"))
    args = parser.parse_args()
    config = run_config(args.params_file, args.device)
    results = []
    for bag in args.bags:
        results.append({"loss": "per_object", **one(bag, config, args.out.parent / bag.name,
                                                    args.true_particles, args.density, args.true_effects)})
        print(json.dumps(plain(results[-1], null_nonfinite=True))[:2000], flush=True)
        if args.ablation:
            union = dataclasses.replace(config, identify=updated(config.identify, {"loss.per_object": False}))
            results.append({"loss": "scene_level",
                            **one(bag, union, args.out.parent / f"{bag.name}_scene_level",
                                  args.true_particles, args.density, args.true_effects)})
            print(json.dumps(plain(results[-1], null_nonfinite=True))[:2000], flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(plain({
        "benchmark": "identify_samples", "device": args.device, "host": platform.node(),
        "python": sys.version.split()[0], "params_file": str(args.params_file),
        "true_particles": args.true_particles, "density": args.density, "true_effects": args.true_effects,
        "results": results}, null_nonfinite=True), indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
