"""Does a bounce depend on the time step? A ball's restitution on the floor and on a slab, per substep count.

    python benchmarks/contact_dissipation.py --out out/contact_dissipation.json [--device cpu]

An elastic ball (radius 4 cm, E 60 kPa, nu 0.3, 1000 kg/m^3, particles at dx/2) falls at 1.5 m/s
onto a frictionless floor, or onto a stiff elastic slab lying on it, and bounces. Nothing in
the model dissipates but the discretisation, so a converged simulator gives a restitution that
does not change as the time step shrinks. The table gives, per grid spacing and per multiple of
the stable substep count (the simulator's own CFL choice is 1), the restitution (the centroid's
largest upward speed after the impact over its largest downward speed before it), the
height (mm) above the floor at which the centroid's fall first slows by 5 % of the free fall's
speed (the contact band: where the floor starts to act), and the lowest height the centroid
reaches, beside the approach Hertz contact gives an elastic sphere at this speed (small-strain
theory, a reference for the squash, not an exact value at 20 % strain). The simulator's floor
and contact conditions act at grid nodes, each substep.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from mosiv_ros.sim import Gravity, Ground, ObjectModel, Particles, SimConfig, Simulator
from mosiv_ros.sim.sampling import box, sphere

G = 9.81
FRAME_DT = 1 / 480
RADIUS = 0.04
SPEED = 1.5
FLOOR = 0.1
SLAB = 0.04  # the slab's thickness
BALL = {"E": 6e4, "nu": 0.3, "density": 1000.0, "friction": 0.0}
SLAB_MATERIAL = {"E": 1e6, "nu": 0.3, "density": 1000.0, "friction": 0.0}


def hertz_approach(on_slab: bool) -> float:
    """The largest approach (m) of the ball's centre to the surface, by Hertz contact theory.

    delta = (15 m v^2 / (16 E* sqrt(R)))^(2/5), 1 / E* = sum of (1 - nu^2) / E over the two bodies
    (the floor rigid; the slab taken as a half-space).
    """
    compliance = sum((1 - p["nu"] ** 2) / p["E"] for p in ([BALL, SLAB_MATERIAL] if on_slab else [BALL]))
    mass = BALL["density"] * 4 / 3 * np.pi * RADIUS**3
    return float((15 * mass * SPEED**2 * compliance / (16 * np.sqrt(RADIUS))) ** 0.4)


def simulator(dx: float, on_slab: bool, device: str) -> tuple[Simulator, float, int]:
    """The drop scene, the height of the surface the ball lands on and the ball's particle count."""
    surface = FLOOR + (SLAB if on_slab else 0.0)
    centre = (0.25, 0.25, surface + RADIUS + 2 * dx)
    ball = sphere(centre, RADIUS, dx / 2)
    solids = [(ball, "ball", BALL)]
    if on_slab:
        slab = box((0.25, 0.25, FLOOR + SLAB / 2), (0.12, 0.12, SLAB / 2), dx / 2)
        solids.append((slab, "slab", SLAB_MATERIAL))
    x = np.concatenate([s[0][0] for s in solids])
    volume = np.concatenate([np.full(len(s[0][0]), s[0][1]) for s in solids])
    index = np.concatenate([np.full(len(s[0][0]), k) for k, s in enumerate(solids)])
    v = np.zeros_like(x)
    v[index == 0, 2] = -SPEED
    config = SimConfig(dx=dx, lo=(0, 0, 0), hi=(0.5, 0.5, 0.4), frame_dt=FRAME_DT,
                       ground=Ground(height=FLOOR, friction=0.0), effects=[Gravity()], device=device)
    objects = [ObjectModel(name, "elastic", params) for _, name, params in solids]
    return Simulator(objects, Particles(x=x, volume=volume, object_index=index, v=v), config), surface, len(ball[0])


def bounce(dx: float, on_slab: bool, scale: int, frames: int, device: str) -> dict:
    """Restitution, contact band and lowest centroid height of one drop at ``scale`` x the stable substeps."""
    sim, surface, n_ball = simulator(dx, on_slab, device)
    stable = sim.time_step()[0]
    path = sim.rollout(frames, substeps=scale * stable)[:, 0]
    z = path[:, :n_ball, 2].mean(axis=1) - surface  # the ball's particles come first
    v = np.diff(z) / FRAME_DT
    low = int(np.argmin(z))
    t = (np.arange(1, len(z)) - 0.5) * FRAME_DT
    free = -(SPEED + G * t)  # the free fall's speed at each interval's middle
    slowed = np.flatnonzero(v[:low] > free[:low] + 0.05 * np.abs(free[:low]))
    band = float((z[slowed[0]] - RADIUS) * 1e3) if len(slowed) else float("nan")
    return {"dx": dx, "on": "slab" if on_slab else "floor", "scale": scale, "substeps": scale * stable,
            "restitution": float(v[low:].max() / -v[:low].min()), "band_mm": band,
            "lowest_mm": float((z[low] - RADIUS) * 1e3), "hertz_mm": -hertz_approach(on_slab) * 1e3}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dx", default="0.02,0.01", help="grid spacings (m)")
    parser.add_argument("--scales", default="1,2,4,8", help="multiples of the stable substep count")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=Path("out/contact_dissipation.json"))
    args = parser.parse_args()
    rows = []
    tick = time.perf_counter()
    print(f"{'dx (m)':>7s} {'on':>5s} {'scale':>5s} {'substeps':>8s} {'restitution':>11s} "
          f"{'band (mm)':>9s} {'lowest (mm)':>11s} {'Hertz (mm)':>10s}")
    for dx in map(float, args.dx.split(",")):
        for on_slab in (False, True):
            for scale in map(int, args.scales.split(",")):
                r = bounce(dx, on_slab, scale, args.frames, args.device)
                rows.append(r)
                print(f"{dx:7.3f} {r['on']:>5s} {scale:5d} {r['substeps']:8d} {r['restitution']:11.3f} "
                      f"{r['band_mm']:9.1f} {r['lowest_mm']:11.1f} {r['hertz_mm']:10.1f}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"benchmark": "contact_dissipation", "host": platform.node(),
                                    "python": platform.python_version(), "device": args.device,
                                    "argv": vars(args) | {"out": str(args.out)}, "frame_dt": FRAME_DT,
                                    "seconds": time.perf_counter() - tick, "rows": rows}, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
