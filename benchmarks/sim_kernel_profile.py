"""Per-kernel wall time of one frame's substeps, forward and adjoint (where the backward goes).

    python benchmarks/sim_kernel_profile.py --device cuda:0 --particles 1000000 --objects 1

Records one frame of substeps on a ``wp.Tape`` (the way ``Simulator.backward`` recomputes a
frame), then replays every recorded launch forward and then every adjoint in reverse order, each
synchronised and timed, and sums the times per kernel. Prints JSON.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import warp as wp
from sim_throughput import build


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="auto")
    parser.add_argument("--particles", type=int, default=100_000)
    parser.add_argument("--objects", type=int, default=1)
    args = parser.parse_args()
    sim = build(args.particles, args.objects, args.device)
    traj = sim.rollout(1, grad=True)
    sim.backward(np.zeros_like(traj))  # allocates the tape buffers, compiles the adjoints
    n_sub, dt = sim._record["n_sub"], sim._record["dt"]
    states, grids, _, _ = sim._tape_buffers_for(n_sub)
    states[0].copy_from(sim._record["checkpoints"][0])
    tape = wp.Tape()
    with tape:
        for s in range(n_sub):
            sim._substep(states[s], states[s + 1], grids[s], s, dt)
    states[-1].x.grad.fill_(1e-3)
    forward: dict[str, float] = {}
    adjoint: dict[str, float] = {}
    for launch in tape.launches:
        kernel, dim, max_blocks, inputs, outputs, device = launch[:6]
        wp.synchronize_device(device)
        start = time.perf_counter()
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device,
                  max_blocks=max_blocks)
        wp.synchronize_device(device)
        forward[kernel.key] = forward.get(kernel.key, 0.0) + time.perf_counter() - start
    for launch in reversed(tape.launches):
        kernel, dim, max_blocks, inputs, outputs, device = launch[:6]
        wp.synchronize_device(device)
        start = time.perf_counter()
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device,
                  adj_inputs=[tape.get_adjoint(a) for a in inputs],
                  adj_outputs=[tape.get_adjoint(a) for a in outputs], adjoint=True,
                  max_blocks=max_blocks)
        wp.synchronize_device(device)
        adjoint[kernel.key] = adjoint.get(kernel.key, 0.0) + time.perf_counter() - start
    print(json.dumps({"particles": sim.n_particles, "objects": args.objects, "substeps": n_sub,
                      "device": sim.device, "forward_s": forward, "adjoint_s": adjoint}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
