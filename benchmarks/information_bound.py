"""How well could any method identify a recording's materials? A Cramér-Rao bound from its truth.

    python benchmarks/information_bound.py bags/elastic_on_plastic bags/sand_and_elastic \\
        --out out/information_bound.json [--sigma 1.0] [--frames 21] [--device cpu]

For each synthetic bag, re-simulates its scene file exactly as the recorder did (the true
parameters, the recorder's particles and grid), then again with one material parameter of one
object moved up and down by a small step (E and yield stress in decades, nu absolute, the
friction angle in degrees), and differences the particle trajectories: the sensitivity of every
particle's position at every frame to every parameter. With each observed position carrying
independent Gaussian noise of ``--sigma`` mm per axis, the Fisher information is J^T J / sigma^2
and no unbiased estimator's standard deviation can be lower than sqrt(diag(F^-1)) (the Cramér-Rao
bound, "jointly": the other parameters unknown too) or 1 / sqrt(F_kk) ("alone": the others
known). Two observation sets: every particle ("volume": more than any camera sees) and the
particles on each object's surface at t = 0 ("surface": what perfect surface tracks on every
side would see). Both are optimistic: real track errors are correlated along a track and
cameras see only part of a surface; the bound scales linearly with sigma.

The opposite case is an error that is not noise: a reconstruction or model error of the same
RMS size at every observation, pointing wherever it moves a parameter most. Least squares then
moves parameter k by up to sqrt(n * (J^T J)^-1_kk) per unit of RMS error (n observed
coordinates): "bias per mm" below, a worst case (an error that is a plain offset or a scaling
of an object moves the estimates less). The RMS error a target tolerates is the target over it.

Also given per parameter: the RMS and largest shift of the surface particles over the frames
for a change of the size of issue 28's targets (0.1 decades in E, 0.05 in nu, 10 % in the
friction angle), to set beside the median track errors of the reconstruction benchmark.

The re-simulation is checked against the recording's ground-truth particles first (largest
difference printed: zero while the simulator's float32 arithmetic is the recorder's, a rounding
error where it has been reordered since, 1.5e-5 mm on bags/pressed_cube after 93354f8); the
steps are small enough for the central differences to be linear (``--step-scale 2`` doubles
them: the bound should barely move).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from mosiv_ros.synth.ground_truth import read_ground_truth, read_ground_truth_particles
from mosiv_ros.synth.layout import lay_out
from mosiv_ros.synth.recorder import simulate
from mosiv_ros.synth.scene_file import read_scene_file

# per parameter: (how it is moved, the step, the size of issue 28's target in the same measure)
PROBES = {
    "E": ("log10", 0.02, 0.1),
    "nu": ("absolute", 0.01, 0.05),
    "yield_stress": ("log10", 0.02, 0.1),
    "friction_angle": ("relative", 0.02, 0.1),
}


def moved(value: float, how: str, delta: float) -> float:
    """``value`` moved by ``delta`` in the measure ``how``."""
    if how == "log10":
        return value * 10.0 ** delta
    if how == "relative":
        return value * (1.0 + delta)
    return value + delta


def surface(rest: np.ndarray, spacing: float) -> np.ndarray:
    """Mask of the lattice points that miss at least one of their six axis neighbours."""
    counts = np.array([len(n) for n in cKDTree(rest).query_ball_point(rest, 1.01 * spacing)])
    return counts < 7  # the point itself and six neighbours


def bound(path: Path, sigma: float, frames: int | None, step_scale: float, device: str | None) -> dict:
    truth = read_ground_truth(path)
    recorded = read_ground_truth_particles(path).positions
    scene_file = Path(truth["scene_file"])
    if not scene_file.is_absolute() and not scene_file.exists():  # relative to the repository
        scene_file = Path(__file__).resolve().parents[1] / scene_file
    spec = read_scene_file(scene_file)
    if device is not None:
        spec.simulation.device = device
    n_frames = spec.n_frames if frames is None else min(frames, spec.n_frames)
    layout = lay_out(spec)
    on_surface = np.concatenate([surface(b.rest, spec.simulation.particle_spacing) for b in layout.bodies])

    started = time.perf_counter()
    base, _ = simulate(layout, n_frames)
    check = float(np.abs(base - recorded[: n_frames + 1]).max())
    print(f"{path.name}: {len(layout.x)} particles ({int(on_surface.sum())} on surfaces), "
          f"{n_frames} frames; re-simulation against the recording: largest difference {check * 1e3:.3g} mm")

    names, columns, shifts = [], [], {}
    for k, obj in enumerate(spec.objects):
        for param, (how, step, target) in PROBES.items():
            if param not in obj.params:
                continue
            h = step * step_scale
            ends = []
            for sign in (1.0, -1.0):
                varied = copy.deepcopy(spec)
                varied.objects[k].params[param] = moved(obj.params[param], how, sign * h)
                ends.append(simulate(lay_out(varied), n_frames)[0])
            column = (ends[0] - ends[1])[1:] / (2 * h)  # (frames, N, 3) per unit of the measure
            name = f"{obj.name}.{param}"
            names.append(name)
            columns.append(column)
            change = np.linalg.norm(column[:, on_surface] * target, axis=-1)
            rms, largest = float(np.sqrt((change**2).mean()) * 1e3), float(change.max() * 1e3)
            shifts[name] = {"target": target, "measure": how, "surface_rms_mm": rms, "surface_max_mm": largest}
            print(f"  {name}: a change of {target:g} ({how}) moves the surface by {rms:.2f} mm RMS, "
                  f"{largest:.2f} mm at most")

    result = {"bag": str(path), "particles": int(len(layout.x)), "surface_particles": int(on_surface.sum()),
              "frames": n_frames, "resimulation_max_diff_mm": check * 1e3, "sigma_mm": sigma,
              "parameters": names, "shift_at_target": shifts, "bounds": {}}
    for observed, mask in (("volume", np.ones(len(layout.x), bool)), ("surface", on_surface)):
        J = np.stack([c[:, mask].reshape(-1) for c in columns], axis=1)  # (observations, parameters)
        fisher = J.T @ J / (sigma * 1e-3) ** 2
        alone = 1.0 / np.sqrt(np.diag(fisher))
        try:
            jointly = np.sqrt(np.diag(np.linalg.inv(fisher)))
        except np.linalg.LinAlgError:
            jointly = np.full(len(names), math.inf)
        per_mm = jointly / sigma * math.sqrt(J.shape[0])
        result["bounds"][observed] = {
            n: {"jointly": float(j), "alone": float(a), "bias_per_mm": float(b),
                "tolerated_mm": shifts[n]["target"] / float(b)}
            for n, j, a, b in zip(names, jointly, alone, per_mm, strict=True)}
        print(f"  {observed} ({int(mask.sum())} particles x {n_frames} frames), sigma {sigma:g} mm:")
        for n, j, a, b in zip(names, jointly, alone, per_mm, strict=True):
            print(f"    {n:28s} std >= {j:.3g} jointly, {a:.3g} alone; up to {b:.3g} per mm RMS error "
                  f"(the target tolerates {shifts[n]['target'] / b:.3g} mm)")
    result["seconds"] = time.perf_counter() - started
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bags", nargs="+", type=Path)
    parser.add_argument("--sigma", type=float, default=1.0, help="noise per observed coordinate, mm")
    parser.add_argument("--frames", type=int, default=None, help="frames after the first (default: all)")
    parser.add_argument("--step-scale", type=float, default=1.0)
    parser.add_argument("--device", default=None, help="simulator device (default: the scene file's)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    results = [bound(b, args.sigma, args.frames, args.step_scale, args.device) for b in args.bags]
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"benchmark": "information_bound", "host": platform.node(),
                                        "python": sys.version.split()[0], "argv": sys.argv[1:],
                                        "results": results}, indent=1))


if __name__ == "__main__":
    main()
