"""The identifier's loss path on a sample bag: a window's loss with its gradient, the batched search.

    python benchmarks/loss_throughput.py bags/elastic_on_plastic --device cuda:0 --compare \\
        --out out/loss_throughput_cuda.json
    python benchmarks/loss_throughput.py bags/elastic_on_plastic --device cpu --rows 2 --repeats 1

Builds the fit problem of each bag as ``mosiv run`` does (reconstruction, lifting, the first 70 %
of the frames; ``--params-file`` gives the node parameters, by default the full budget of
``config/mosiv.yaml``), starts from the problem's initial point (the observed initial
velocities) and times:

- ``window``: ``Identifier.window_loss`` over the whole fitted window with its gradient, split
  as the fit's history splits an iteration (``Identifier.timing``: simulation forward, loss,
  backward; on a GPU the loss is queued behind the forward, whose time then holds it, and the
  loss's is the host's part); two untimed calls first (kernel compilation, CUDA graph capture);
- ``window_torch_ops``: the torch operations one such call issues on the tensor path (host work
  on a GPU grows with them; the CPU's count is higher: it renders the silhouettes in smaller
  batches, ``losses.SPLAT_BATCH``);
- ``search``: ``GlobalSearch.batch_object_losses`` of ``--rows`` candidate rows drawn uniformly
  from the search's first box (``GlobalSearch.box``: the material parameters' prior ranges),
  as the search scores them by default (on a GPU one batch at the stiffest row's time step, on
  the CPU each row at its own), split into rollout and scoring (``GlobalSearch.timing``; on a
  GPU the scoring is queued behind the rollout, whose time then holds it); one untimed call
  first.

The losses are computed as the identifier chooses (``Identifier.tensor_device``: as tensors on
a GPU, by KD-trees on the CPU); ``--compare`` times both paths on the same device, interleaved
(tensors, KD-trees, tensors, ...); ``--tapes`` times the window again with every frame's tape
kept by the rollout and with each frame recomputed by the backward (``SimConfig.tape_memory``),
alternating, each round after two untimed calls. Each figure is the mean of ``--repeats`` timed calls (their
minimum too). ``--kernels`` (a CUDA device only) also replays one window and one search call
under torch's profiler, whose CUPTI records every kernel, those of CUDA graphs included, and
gives each kernel's device time per substep (the launches of G2P's forward count the
substeps), and where the device waits: its idle time between neighbouring kernels, copies and
memsets, summed by the pair (``device_idle``). The losses themselves are in the JSON, to compare
paths and devices. Writes JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile

from mosiv_ros.cli import run_config
from mosiv_ros.identify.fit import FitSettings, Identifier
from mosiv_ros.identify.problem import build_problem, views_of
from mosiv_ros.identify.run import problem_options
from mosiv_ros.io.files import plain
from mosiv_ros.pipeline import fit_window
from mosiv_ros.prepare import RunConfig, prepare
from mosiv_ros.sim.runtime import resolve_device


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


def timed(identifier: Identifier, paths: dict[str, str | None], call, timing, repeats: int) -> dict:
    """``call()`` ``repeats`` times on each loss path, the paths interleaved (A, B, A, B).

    ``paths`` names the ``Identifier.tensor_device`` of each; per path the mean and least wall
    time, the mean of each of ``timing()``'s parts, and the last call's result.
    """
    runs = {name: [] for name in paths}
    for _ in range(repeats):
        for name, device in paths.items():
            identifier.tensor_device = device
            tick = time.perf_counter()
            result = call()
            runs[name].append((time.perf_counter() - tick, dict(timing()), result))
    return {name: {"wall_s": float(np.mean([w for w, _, _ in r])), "wall_min_s": float(np.min([w for w, _, _ in r])),
                   **{key: float(np.mean([t[key] for _, t, _ in r])) for key in r[0][1]}, "result": r[-1][2]}
            for name, r in runs.items()}


def torch_ops(call) -> int:
    """The torch operations ``call()`` issues at the top level (an autograd node's backward is one)."""
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        call()
    return sum(1 for event in prof.events() if event.cpu_parent is None)


def kernel_name(name: str) -> str:
    """A kernel's name without Warp's module hash (``_forward``/``_backward``: Warp's two versions of one kernel)."""
    return re.sub(r"_[0-9a-f]{8}_cuda_kernel_", "_", name)[:80]


DEVICE_WORK = ("kernel", "gpu_memcpy", "gpu_memset")
"""The categories of a torch profiler trace's events that the device runs."""


def device_idle(events: list[dict], most: int = 8) -> dict:
    """Where the device waits in a trace: its span, busy and idle time, and the idle time between neighbours.

    ``events``: a torch profiler trace's ``traceEvents``; those the device runs (``DEVICE_WORK``)
    count, each from ``ts`` for ``dur`` (us). A gap is the time from the latest end so far to
    the next start; the gaps are summed by the pair of names around them (the event that ended
    last, the one that starts), and the ``most`` pairs with the most idle time are given, most
    first, with how often each pair met.
    """
    work = sorted((e for e in events if e.get("cat") in DEVICE_WORK and "dur" in e), key=lambda e: e["ts"])
    pairs: dict[tuple[str, str], list] = {}
    idle, latest = 0.0, None  # latest: (end, name) of the event that ends last so far
    for event in work:
        name, end = kernel_name(event["name"]), event["ts"] + event["dur"]
        if latest is not None:
            gap = max(event["ts"] - latest[0], 0.0)
            idle += gap
            pair = pairs.setdefault((latest[1], name), [0, 0.0])
            pair[0] += 1
            pair[1] += gap
        if latest is None or end >= latest[0]:
            latest = (end, name)
    span = latest[0] - work[0]["ts"] if work else 0.0
    gaps = sorted(pairs.items(), key=lambda item: -item[1][1])[:most]
    return {"span_us": span, "busy_us": span - idle, "idle_us": idle,
            "gaps": [{"after": a, "before": b, "count": n, "idle_us": us} for (a, b), (n, us) in gaps]}


def refuse_without_cuda(parser: argparse.ArgumentParser, device: str) -> None:
    """End with ``parser``'s error unless ``device`` is a CUDA device: ``kernel_times`` needs one."""
    if not resolve_device(device).startswith("cuda"):
        parser.error(f"--kernels needs a CUDA device, not {device!r}: on the CPU torch's profiler does not "
                     "see Warp's kernels (benchmarks/sim_kernel_profile.py times them one launch at a time)")


def kernel_times(call) -> dict:
    """Each kernel's device time over ``call()`` on a GPU, per substep, and where the device waits, by torch's profiler.

    Kernels are named without Warp's module hash (``kernel_name``); ``substeps`` counts the
    launches of G2P's forward, one a substep (twice where a backward recomputes its frames,
    which the tapes a rollout keeps spare); ``idle``: ``device_idle`` of the call's trace.
    """
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        call()
        torch.cuda.synchronize()
    kernels: dict[str, list] = {}
    for event in prof.events():
        if event.device_type == torch.autograd.DeviceType.CUDA:
            launches = kernels.setdefault(kernel_name(event.name), [0, 0.0])
            launches[0] += 1
            launches[1] += event.device_time
    with tempfile.TemporaryDirectory() as folder:
        trace = Path(folder) / "trace.json"
        prof.export_chrome_trace(str(trace))
        events = json.loads(trace.read_text())["traceEvents"]
    substeps = kernels.get("g2p_forward", [0])[0]
    return {"substeps": substeps, "device_us": sum(us for _, us in kernels.values()),
            "per_substep_us": {name: us / max(substeps, 1)
                               for name, (_, us) in sorted(kernels.items(), key=lambda k: -k[1][1])},
            "launches": {name: n for name, (n, _) in kernels.items()}, "idle": device_idle(events)}


def one(bag: Path, config: RunConfig, rows: int, repeats: int, compare: bool, tapes: bool,
        kernels: bool = False) -> dict:
    identifier, velocity = identifier_of(bag, config)
    obs = identifier.problem.observations
    n = obs.n_frames - 1
    paths = ({"tensor": identifier.tensor_device or "cpu", "kdtree": None} if compare
             else {"tensor" if identifier.tensor_device else "kdtree": identifier.tensor_device})

    u = identifier.pack()

    def window() -> dict:
        identifier.apply(u, velocity)  # the search's calls set the simulator to their first row
        loss, du, _, per = identifier.window_loss(0, n, None, grad=True)
        return {"loss": loss, "per_object": per.tolist(), "du": du.tolist()}

    lo, hi = identifier.search.box(u)
    candidates = lo + (hi - lo) * np.random.default_rng(0).random((rows, len(u)))

    def search() -> dict:
        total, per = identifier.search.batch_object_losses(candidates, velocity)
        return {"loss": total.tolist(), "per_object": per.tolist()}

    # untimed: kernel compilation, the CUDA graphs' capture (a window's second call), the batched
    # simulator's buffers, the observations' tensors
    timed(identifier, paths, window, lambda: {}, 2)
    timed(identifier, paths, search, lambda: {}, 1)
    kept = bool(identifier.sim.kept_tape_frames)
    ops = {}
    for name, device in paths.items():  # what a window's loss issues to torch, whatever each costs
        if device is not None:
            identifier.tensor_device = device
            ops[name] = torch_ops(window)
    result = {"bag": str(bag), "device": identifier.sim.device, "particles": len(identifier.index),
              "window_torch_ops": ops,
              "frames": n, "free": [e.label for e in identifier.entries], "rows": rows,
              "observed_points": int(sum(len(p) for frame in obs.points[1:] for p in frame)),
              "window": timed(identifier, paths, window, lambda: identifier.timing, repeats),
              "search": timed(identifier, paths, search, lambda: identifier.search.timing, repeats),
              "tapes_kept": kept}
    if tapes:  # kept and recomputed frames have CUDA graphs of their own: untimed calls first
        result["tapes"] = []
        for _ in range(2):
            for memory in (None, 0.0):
                identifier.sim.config.tape_memory = memory
                timed(identifier, paths, window, lambda: {}, 2)
                result["tapes"].append({"tape_memory": memory, "kept": bool(identifier.sim.kept_tape_frames),
                                        **timed(identifier, paths, window, lambda: identifier.timing, repeats)})
        identifier.sim.config.tape_memory = None
    if kernels:
        result["kernels"] = {"window": kernel_times(window), "search": kernel_times(search)}
        for part, times in result["kernels"].items():
            print("kernels", part, times["substeps"], "substeps",
                  {name: round(us, 2) for name, us in list(times["per_substep_us"].items())[:8]}, flush=True)
            idle = times["idle"]
            print("idle", part, f"span {idle['span_us'] / 1e3:.1f} ms, busy {idle['busy_us'] / 1e3:.1f} ms;",
                  "; ".join(f"{g['after']} -> {g['before']}: {g['idle_us'] / 1e3:.2f} ms over {g['count']}"
                            for g in idle["gaps"][:4]), flush=True)
    parts = ("window", "search") + (("tapes",) if tapes else ())
    for part in parts:
        rounds = result[part] if part == "tapes" else [result[part]]
        for r in rounds:
            print(part, json.dumps({name: ({k: v for k, v in value.items() if k != "result"}
                                           if isinstance(value, dict) else value)
                                    for name, value in r.items()}), flush=True)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bags", nargs="+", type=Path)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--params-file", type=Path, default=Path("config/mosiv.yaml"))
    parser.add_argument("--rows", type=int, default=32, help="candidate rows of the batched search")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--compare", action="store_true",
                        help="time both loss paths, the tensors' and the KD-trees', interleaved")
    parser.add_argument("--tapes", action="store_true",
                        help="time the window again with its frames' tapes kept by the rollout "
                             "(SimConfig.tape_memory's default) and recomputed by the backward (0), "
                             "two rounds each")
    parser.add_argument("--kernels", action="store_true",
                        help="also each kernel's device time a substep, of a window and a search call "
                             "(torch's profiler; a CUDA device only)")
    parser.add_argument("--out", type=Path, default=Path("out/loss_throughput.json"))
    args = parser.parse_args()
    config = run_config(args.params_file, args.device)
    if args.kernels:
        refuse_without_cuda(parser, config.identify.device)
    results = [one(bag, config, args.rows, args.repeats, args.compare, args.tapes, args.kernels)
               for bag in args.bags]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(plain({
        "benchmark": "loss_throughput", "device": args.device, "host": platform.node(),
        "python": sys.version.split()[0], "argv": sys.argv[1:], "params_file": str(args.params_file),
        "results": results}, null_nonfinite=True), indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
