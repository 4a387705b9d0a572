"""Does the simulator's ball roll? Its acceleration down a slope against a rolling sphere's.

    python benchmarks/rolling_ball.py --out out/rolling_ball.json [--device cpu]

A solid elastic sphere set on a flat floor under gravity tilted by ``--slope`` degrees (the
floor friction 0.5, far above the slope's tangent, so a block would stick) rolls without
slipping at a = 5/7 g sin(theta) and slides, frictionless, at g sin(theta). For each diameter
(in cells of dx) and each height of the floor within a cell (the fraction of dx between the
floor and the layer of grid nodes below it; domains snap to multiples of dx, so a floor at a
multiple of dx, such as 0, runs through a layer of nodes: fraction 0), the table gives the
acceleration fitted to the centroid's path down the slope after the first 0.15 s. The
simulator's floor condition acts at grid nodes, which is why the fraction matters.

What any change of the floor condition must keep: ``--blocks`` adds a 10 x 8 x 4 cm block on a
30-degree slope (dx 2 cm) at each floor height, which slides at g (sin - mu cos) for mu 0.2 and
0.4 and sticks for mu 0.8 (its drift over the last 10 frames of 20 ms, which should be 0).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from pathlib import Path

import numpy as np

from mosiv_ros.sim import Gravity, Ground, ObjectModel, Particles, SimConfig, Simulator
from mosiv_ros.sim.sampling import box, sphere

G = 9.81
FRAME_DT = 1 / 30


def slope_acceleration(path: np.ndarray, frame_dt: float, settle: float) -> float:
    """Constant acceleration (m/s^2) fitted to a path along the slope (frames,) after ``settle`` seconds."""
    t = np.arange(len(path)) * frame_dt
    keep = t >= settle
    return float(2.0 * np.polyfit(t[keep], path[keep], 2)[0])


def acceleration(diameter: float, dx: float, fraction: float, slope: float, frames: int, device: str) -> float:
    """Fitted acceleration (m/s^2) down the slope of a ball resting on a floor ``fraction`` dx above a node layer."""
    floor = 0.1 + fraction * dx
    radius = diameter / 2
    x, volume = sphere((0.2, 0.2, floor + radius + 1e-3), radius, dx / 2)
    theta = math.radians(slope)
    gravity = (G * math.sin(theta), 0.0, -G * math.cos(theta))
    config = SimConfig(dx=dx, lo=(0.0, 0.0, 0.0), hi=(0.2 + 0.5, 0.4, floor + diameter + 0.1),
                       frame_dt=FRAME_DT, ground=Ground(height=floor, friction=0.5),
                       effects=[Gravity(g=gravity)], device=device)
    particles = Particles(x=x, volume=np.full(len(x), volume), object_index=np.zeros(len(x), dtype=int))
    sim = Simulator([ObjectModel("ball", "elastic", {"E": 6e4, "nu": 0.35})], particles, config)
    path = sim.rollout(frames)[:, 0, :, 0].mean(axis=1)
    return slope_acceleration(path, FRAME_DT, 0.15)


def block(fraction: float, mu: float, device: str) -> tuple[float, float]:
    """(fitted acceleration, drift over the last 10 frames) of a block on a 30-degree slope."""
    dx, theta = 0.02, math.radians(30)
    floor = 0.1 + fraction * dx
    x, volume = box((0.15, 0.15, floor + 0.02), (0.05, 0.04, 0.02), dx / 2)
    config = SimConfig(dx=dx, lo=(0.0, 0.0, 0.0), hi=(0.6, 0.3, 0.3), frame_dt=0.02,
                       ground=Ground(height=floor, friction=mu),
                       effects=[Gravity(g=(G * math.sin(theta), 0.0, -G * math.cos(theta)))], device=device)
    particles = Particles(x=x, volume=np.full(len(x), volume), object_index=np.zeros(len(x), dtype=int))
    sim = Simulator([ObjectModel("block", "elastic", {"E": 2e5})], particles, config)
    path = sim.rollout(15)[:, 0, :, 0].mean(axis=1)
    return slope_acceleration(path, 0.02, 0.06), float(path[-1] - path[5])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--slope", type=float, default=9.0, help="degrees")
    parser.add_argument("--frames", type=int, default=18)
    parser.add_argument("--diameter", type=float, default=0.05, help="m")
    parser.add_argument("--cells", type=float, nargs="+", default=[2.5, 5.0, 7.5, 10.0],
                        help="diameters in cells of dx")
    parser.add_argument("--fractions", type=float, nargs="+", default=[0.0, 0.25, 0.5, 0.75],
                        help="heights of the floor above a node layer, in dx")
    parser.add_argument("--blocks", action="store_true", help="also the sliding and sticking block")
    parser.add_argument("--out", type=Path, default=Path("out/rolling_ball.json"))
    args = parser.parse_args()
    rolling = 5 / 7 * G * math.sin(math.radians(args.slope))
    rows = []
    print(f"rolling without slipping: {rolling:.3f} m/s^2; sliding without friction: "
          f"{G * math.sin(math.radians(args.slope)):.3f}")
    print("| cells across | floor above a node layer (dx) | acceleration (m/s^2) | / rolling | time (s) |")
    print("| --- | --- | --- | --- | --- |")
    for cells in args.cells:
        for fraction in args.fractions:
            tick = time.perf_counter()
            a = acceleration(args.diameter, args.diameter / cells, fraction, args.slope, args.frames, args.device)
            rows.append({"cells": cells, "fraction": fraction, "acceleration": a, "ratio": a / rolling,
                         "seconds": time.perf_counter() - tick})
            print(f"| {cells:g} | {fraction:g} | {a:.3f} | {a / rolling:.2f} | {rows[-1]['seconds']:.1f} |")
    blocks = []
    if args.blocks:
        print("| block: floor above a node layer (dx) | mu | acceleration (m/s^2) | expected | drift (mm) |")
        print("| --- | --- | --- | --- | --- |")
        for fraction in args.fractions:
            for mu in (0.2, 0.4, 0.8):
                a, drift = block(fraction, mu, args.device)
                expected = max(0.0, G * (math.sin(math.radians(30)) - mu * math.cos(math.radians(30))))
                blocks.append({"fraction": fraction, "mu": mu, "acceleration": a, "expected": expected,
                               "drift_m": drift})
                print(f"| {fraction:g} | {mu:g} | {a:.3f} | {expected:.3f} | {drift * 1e3:.2f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"benchmark": "rolling_ball", "device": args.device, "host": platform.node(),
                                    "slope_deg": args.slope, "diameter_m": args.diameter, "rolling": rolling,
                                    "rows": rows, "blocks": blocks}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
