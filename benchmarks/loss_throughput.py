"""The identifier's loss path on a sample bag: a window's loss with its gradient, the batched search.

    python benchmarks/loss_throughput.py bags/elastic_on_plastic --device cuda:0 \\
        --out out/loss_throughput_cuda.json
    python benchmarks/loss_throughput.py bags/elastic_on_plastic --device cpu --rows 2 --repeats 1

Builds the fit problem of each bag as ``mosiv run`` does (reconstruction, lifting, the first 70 %
of the frames; ``--params-file`` gives the node parameters, by default the full budget of
``config/mosiv.yaml``), starts from the problem's initial point (the observed initial
velocities) and times:

- ``window``: ``Identifier.window_loss`` over the whole fitted window with its gradient, split
  as the fit's history splits an iteration (``Identifier.timing``: simulation forward, loss,
  backward); two untimed calls first (kernel compilation, CUDA graph capture);
- ``search``: ``GlobalSearch.batch_object_losses`` of ``--rows`` candidate rows drawn uniformly
  from the search's first box (``GlobalSearch.box``: the material parameters' prior ranges),
  as the search scores them by default (on a GPU one batch at the stiffest row's time step, on
  the CPU each row at its own), split into rollout and scoring (``GlobalSearch.timing``); one
  untimed call first.

Each figure is the mean of ``--repeats`` timed calls (their minimum too). The losses themselves
are in the JSON, to compare devices. Writes JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from mosiv_ros.cli import run_config
from mosiv_ros.identify.fit import FitSettings, Identifier
from mosiv_ros.identify.problem import build_problem, views_of
from mosiv_ros.identify.run import problem_options
from mosiv_ros.io.files import plain
from mosiv_ros.pipeline import fit_window
from mosiv_ros.prepare import RunConfig, prepare


def identifier_of(bag: Path, config: RunConfig) -> tuple[Identifier, np.ndarray]:
    """The identifier of ``bag``'s fit problem, set to its initial point, and the initial velocities."""
    prepared = prepare(bag, config)
    views = views_of(prepared.recording)
    window = fit_window(len(prepared.frames), config.holdout)
    problem = build_problem(prepared.frames[:window], prepared.lifted, prepared.recording.scene, views,
                            prepared.recording.gripper_poses, problem_options(config.identify, views))
    problem.sim_config.device = config.identify.device
    identifier = Identifier(problem, FitSettings.of(config.identify))
    obs = problem.observations
    velocity = np.zeros((obs.n_objects, 6))
    velocity[:, :3] = obs.initial_velocities()
    identifier.apply(identifier.pack(), velocity)
    return identifier, velocity


def timed(call, timing: dict, repeats: int) -> dict:
    """``call()`` ``repeats`` times: mean and least wall time, mean of each of ``timing``'s parts."""
    walls, parts = [], []
    for _ in range(repeats):
        tick = time.perf_counter()
        call()
        walls.append(time.perf_counter() - tick)
        parts.append(dict(timing()))
    return {"wall_s": float(np.mean(walls)), "wall_min_s": float(np.min(walls)),
            **{key: float(np.mean([p[key] for p in parts])) for key in parts[0]}}


def one(bag: Path, config: RunConfig, rows: int, repeats: int) -> dict:
    identifier, velocity = identifier_of(bag, config)
    obs = identifier.problem.observations
    n = obs.n_frames - 1

    def window() -> tuple:
        return identifier.window_loss(0, n, None, grad=True)

    for _ in range(2):  # kernel compilation, then the CUDA graphs' capture
        loss, du, dv, per = window()
    result = {"bag": str(bag), "device": identifier.sim.device, "particles": len(identifier.index),
              "frames": n, "free": [e.label for e in identifier.entries],
              "observed_points": int(sum(len(p) for frame in obs.points[1:] for p in frame)),
              "window": {**timed(window, lambda: identifier.timing, repeats),
                         "loss": float(loss), "per_object": per.tolist(), "du": du.tolist()}}
    print(json.dumps(result["window"]), flush=True)
    u = identifier.pack()
    lo, hi = identifier.search.box(u)
    candidates = lo + (hi - lo) * np.random.default_rng(0).random((rows, len(u)))
    scores = {}

    def search() -> None:
        scores["total"], scores["per"] = identifier.search.batch_object_losses(candidates, velocity)

    search()  # compilation, the batched simulator's buffers
    result["search"] = {"rows": rows, **timed(search, lambda: identifier.search.timing, repeats),
                        "loss": scores["total"].tolist(), "per_object": scores["per"].tolist()}
    print(json.dumps(plain(result["search"], null_nonfinite=True))[:600], flush=True)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bags", nargs="+", type=Path)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--params-file", type=Path, default=Path("config/mosiv.yaml"))
    parser.add_argument("--rows", type=int, default=32, help="candidate rows of the batched search")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("out/loss_throughput.json"))
    args = parser.parse_args()
    config = run_config(args.params_file, args.device)
    results = [one(bag, config, args.rows, args.repeats) for bag in args.bags]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(plain({
        "benchmark": "loss_throughput", "device": args.device, "host": platform.node(),
        "python": sys.version.split()[0], "argv": sys.argv[1:], "params_file": str(args.params_file),
        "results": results}, null_nonfinite=True), indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
