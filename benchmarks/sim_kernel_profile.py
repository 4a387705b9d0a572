"""Per-kernel wall time of one frame's substeps, forward and adjoint, against the whole frame.

    python benchmarks/sim_kernel_profile.py --device cuda:0 --particles 1000000 --objects 1

Records one frame of substeps on a ``wp.Tape`` (the way ``Simulator.backward`` recomputes a
frame), then replays every recorded launch forward and then every adjoint in reverse order, each
synchronised and timed, and sums the times per kernel. A forward replay repeats a recorded
command (``wp.Launch``), so it times the kernel alone; an adjoint runs as ``Simulator.backward``
runs it (``Simulator._adjoint_of``: G2P's written adjoint, the others Warp's, each on one thread
here; on the CPU their packed arguments are kept after the first of the repeats). ``frame_s``
times one whole frame of ``Simulator.rollout`` and of ``Simulator.backward`` (which recomputes
the frame, then runs its adjoint), and ``outside_kernels_s`` what of it the kernels above do
not account for: zeroing, the active box, launching, Python (for the backward, where the CPU
runs P2G's adjoint in two parts side by side, this can be negative). Prints JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import warp as wp
from sim_throughput import build


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="auto")
    parser.add_argument("--particles", type=int, default=100_000)
    parser.add_argument("--objects", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3,
                        help="every time is the least of this many (shared machines are noisy)")
    args = parser.parse_args()
    sim = build(args.particles, args.objects, args.device, 0.0)
    traj = sim.rollout(1, grad=True)
    sim.backward(np.zeros_like(traj))  # allocates the tape buffers, compiles the adjoints
    frame = {"forward": math.inf, "backward": math.inf}
    for _ in range(args.repeats):
        start = time.perf_counter()
        sim.rollout(1)
        frame["forward"] = min(frame["forward"], time.perf_counter() - start)
        traj = sim.rollout(1, grad=True)
        start = time.perf_counter()
        sim.backward(np.full_like(traj, 1e-3))
        frame["backward"] = min(frame["backward"], time.perf_counter() - start)
    n_sub = sim._record["n_sub"]
    recorded = sim._tape_buffers_for(n_sub)[0]
    states, grids = recorded.states, recorded.grids
    states[0].copy_from(sim._record["checkpoints"][0])
    tape = wp.Tape()
    with tape:
        for s in range(n_sub):
            sim._substep(states[s], states[s + 1], grids[s], s)
    states[-1].x.grad.fill_(1e-3)
    forward: dict[str, float] = {}
    adjoint: dict[str, float] = {}
    for _ in range(args.repeats):
        once: dict[str, float] = {}
        for launch in tape.launches:
            kernel, dim, max_blocks, inputs, outputs, device = launch[:6]
            command = wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device,
                                max_blocks=max_blocks, record_cmd=True)
            wp.synchronize_device(device)
            start = time.perf_counter()
            command.launch()
            wp.synchronize_device(device)
            once[kernel.key] = once.get(kernel.key, 0.0) + time.perf_counter() - start
        forward = {k: min(t, forward.get(k, math.inf)) for k, t in once.items()}
        once = {}
        for position, launch in enumerate(reversed(tape.launches)):
            kernel, device = launch[0], launch[5]
            wp.synchronize_device(device)
            start = time.perf_counter()
            sim._adjoint_of(launch, tape, ("profile", position))
            wp.synchronize_device(device)
            once[kernel.key] = once.get(kernel.key, 0.0) + time.perf_counter() - start
        adjoint = {k: min(t, adjoint.get(k, math.inf)) for k, t in once.items()}
    outside = {"forward": frame["forward"] - sum(forward.values()),
               "backward": frame["backward"] - sum(forward.values()) - sum(adjoint.values())}
    print(json.dumps({"particles": sim.n_particles, "objects": args.objects, "substeps": n_sub,
                      "device": sim.device, "forward_s": forward, "adjoint_s": adjoint,
                      "frame_s": frame, "outside_kernels_s": outside}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
