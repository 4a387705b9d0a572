"""Simulator throughput and memory: forward and forward+backward, per particle count and device.

    python benchmarks/sim_throughput.py --device cuda:0 --out out/sim_throughput_cuda.json
    python benchmarks/sim_throughput.py --device cpu --particles 10000 100000

Scenes: one or two elastic blocks (8 particles per cell) dropped onto the ground. Each
configuration runs in its own subprocess (so that its peak memory is its own): a warm-up of two
rollouts of ``--frames`` frames with their backward passes and two frames forward (kernel
compilation; on a GPU the capture of the frame's and the backward's CUDA graphs, which an
identification replays hundreds of times), then ``--frames`` timed frames forward only, then the
same frames with checkpoints (or with every frame's tape kept, where ``--tape-memory`` GB hold
them: ``SimConfig.tape_memory``) plus the backward pass of a random dL/dx. Throughput is
particle-substeps per second (particles x substeps / wall time). Peak memory: GPU, the largest
drop of the device's free memory while the configuration ran; CPU, the subprocess's peak resident
set size. A ``frames_scaling`` entry repeats forward+backward of the middle configuration with
twice the frames, to show memory grows with frames (checkpoints), not substeps.

``--batch B`` (B > 1) measures the search's case instead: B parameter sets of each scene in one
batched rollout, Young's modulus spread log-uniformly over a decade up to the single scene's
(so that the batch steps at that scene's time step), forward only (the search takes no
gradients); throughput counts every row's particles.

    python benchmarks/sim_throughput.py --device cuda:0 --particles 3000 --objects 1 2 --batch 32

``--kernels`` (a CUDA device only) replays the timed forward frames once more under torch's
profiler and adds each kernel's device time per substep and where the device waits
(``loss_throughput.kernel_times``).
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

STIFFEST = 5e4
"""Young's modulus (Pa) of the blocks; a batch's stiffest row."""


def build(n_particles: int, n_objects: int, device: str, tape_memory: float, batch: int = 1):
    import numpy as np

    from mosiv_ros.sim import Ground, ObjectModel, Particles, SimConfig, Simulator, domain_around
    from mosiv_ros.sim.sampling import box

    dx = 0.01
    spacing = dx / 2
    per_object = n_particles // n_objects
    side = round(per_object ** (1 / 3)) * spacing  # a cube of per_object particles
    solids = [box((0.0, k * (side + 4 * dx), 0.1 + side / 2), (side / 2,) * 3, spacing)[0]
              for k in range(n_objects)]
    x = np.concatenate(solids)
    index = np.concatenate([np.full(len(s), k) for k, s in enumerate(solids)])
    lo, hi = domain_around(x, dx, margin=0.05, floor=0.1)
    config = SimConfig(dx=dx, lo=lo, hi=hi, frame_dt=1 / 30, ground=Ground(height=0.1),
                       device=device, max_speed=2.0, tape_memory=tape_memory)
    objects = [ObjectModel(f"block{k}", "elastic", {"E": STIFFEST}) for k in range(n_objects)]
    sim = Simulator(objects, Particles(x=x, volume=spacing**3, object_index=index), config, n_batch=batch)
    if batch > 1:  # the search's rows: moduli over a decade, the stiffest the single scene's
        sim.params.set("E", (STIFFEST * np.logspace(-1, 0, batch))[:, None])
    return sim


def run_one(n_particles: int, n_objects: int, frames: int, device: str, tape_memory: float,
            batch: int = 1, kernels: bool = False) -> dict:
    import numpy as np
    import warp as wp

    sim = build(n_particles, n_objects, device, tape_memory, batch)
    forward_only = batch > 1  # the search's case takes no gradients
    cuda = sim.device.startswith("cuda")
    free0 = wp.get_device(sim.device).free_memory if cuda else 0
    lowest = [free0]

    def sample():  # after each run: the buffers a run allocates are kept by the simulator
        if cuda:
            lowest[0] = min(lowest[0], wp.get_device(sim.device).free_memory)

    n_sub, _ = sim.time_step()
    rng = np.random.default_rng(0)
    # warm-up: compilation and the CUDA graphs' captures, each on its graph's second run (a
    # rollout's first frame has a graph of its own when the tapes are kept)
    for _ in range(2):
        traj = sim.rollout(frames, grad=not forward_only)
        if not forward_only:
            sim.backward(rng.normal(size=traj.shape).astype(np.float32) * 1e-3)
    sim.rollout(2)
    sample()
    start = time.perf_counter()
    sim.rollout(frames)
    forward = time.perf_counter() - start
    sample()
    work = sim.n_batch * sim.n_particles * n_sub * frames
    result = {
        "particles": sim.n_particles, "objects": n_objects, "batch": sim.n_batch,
        "grid_nodes": sim.n_nodes * n_objects, "frames": frames, "substeps_per_frame": n_sub,
        "device": sim.device, "tapes_kept": bool(sim.kept_tape_frames),
        "forward_s": forward, "forward_particle_substeps_per_s": work / forward,
    }
    if kernels:  # a CUDA device (``main`` refuses others)
        from loss_throughput import kernel_times  # torch's profiler, only where asked

        result["kernels"] = kernel_times(lambda: sim.rollout(frames))
    if not forward_only:
        dL = rng.normal(size=traj.shape).astype(np.float32) * 1e-3  # drawn untimed (0.3 s at 1M particles)
        start = time.perf_counter()
        sim.rollout(frames, grad=True)
        sim.backward(dL)
        sample()
        both = time.perf_counter() - start
        result.update({"forward_backward_s": both, "forward_backward_particle_substeps_per_s": work / both,
                       "backward_over_forward": (both - forward) / forward})
    peak = (free0 - lowest[0]) if cuda else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {**result, "peak_memory_bytes": int(peak), "peak_memory_kind": "device" if cuda else "process RSS"}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="auto")
    parser.add_argument("--particles", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    parser.add_argument("--objects", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--frames", type=int, default=2)
    parser.add_argument("--tape-memory", type=float, default=0.0,
                        help="SimConfig.tape_memory, GB (default 0: every frame recomputed by the "
                             "backward, memory growing with frames, not substeps)")
    parser.add_argument("--out", type=Path, default=None, help="write the JSON here too")
    parser.add_argument("--batch", type=int, default=1,
                        help="parameter sets in one batched rollout, forward only (the search's case)")
    parser.add_argument("--kernels", action="store_true",
                        help="each kernel's device time per substep of the forward frames (a CUDA device only)")
    parser.add_argument("--one", nargs=3, type=int, metavar=("N", "K", "FRAMES"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.kernels:
        from loss_throughput import refuse_without_cuda

        refuse_without_cuda(parser, args.device)
    if args.one:
        print(json.dumps(run_one(*args.one, args.device, args.tape_memory, args.batch, args.kernels)))
        return 0
    results = []
    for n in args.particles:
        for k in args.objects:
            results.append(_child(n, k, args.frames, args.device, args.tape_memory, args.batch, args.kernels))
            print(json.dumps(results[-1]), flush=True)
    middle = args.particles[len(args.particles) // 2]
    scaling = [] if args.batch > 1 else [_child(middle, 1, f, args.device, args.tape_memory)
                                         for f in (args.frames, 2 * args.frames)]
    report = {"benchmark": "sim_throughput", "host": platform.node(), "python": sys.version.split()[0],
              "results": results,
              "frames_scaling": [{"frames": r["frames"], "peak_memory_bytes": r["peak_memory_bytes"],
                                  "substeps_per_frame": r["substeps_per_frame"]} for r in scaling]}
    text = json.dumps(report, indent=2)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    return 0


def _child(n: int, k: int, frames: int, device: str, tape_memory: float, batch: int = 1,
           kernels: bool = False) -> dict:
    out = subprocess.run([sys.executable, __file__, "--device", device, "--tape-memory", str(tape_memory),
                          "--batch", str(batch), *(["--kernels"] if kernels else []),
                          "--one", str(n), str(k), str(frames)],
                         capture_output=True, text=True, check=False)
    if out.returncode != 0:
        # a negative code is the signal that ended it (-9: killed, typically out of memory)
        return {"particles": n, "objects": k, "frames": frames, "exit_code": out.returncode,
                "error": out.stderr[-2000:]}
    return json.loads(out.stdout.strip().splitlines()[-1])


if __name__ == "__main__":
    raise SystemExit(main())
