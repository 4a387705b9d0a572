"""Small simulator scenes shared by the simulator tests (CPU-sized: a few thousand particles).

The tests run on the CPU; ``MOSIV_TEST_DEVICE=cuda:0`` runs the same checks on a GPU.
"""

from __future__ import annotations

import os

import numpy as np

from mosiv_ros.sim import Ground, ObjectModel, Particles, SimConfig, Simulator
from mosiv_ros.sim.sampling import box, sphere

DEVICE = os.environ.get("MOSIV_TEST_DEVICE", "cpu")


def scene(solids, objects, *, dx, lo, hi, frame_dt=0.02, ground=None, effects=None,
          colliders=(), velocities=None, n_batch=1, **config) -> Simulator:
    """A simulator of several solids: ``solids`` is a list of (positions, particle volume)."""
    x = np.concatenate([s[0] for s in solids])
    volume = np.concatenate([np.full(len(s[0]), s[1]) for s in solids])
    index = np.concatenate([np.full(len(s[0]), k) for k, s in enumerate(solids)])
    v = None
    if velocities is not None:
        v = np.concatenate([np.tile(np.asarray(vk, float), (len(s[0]), 1))
                            for s, vk in zip(solids, velocities, strict=True)])
    kwargs = {} if effects is None else {"effects": list(effects)}
    cfg = SimConfig(dx=dx, lo=lo, hi=hi, frame_dt=frame_dt, ground=ground,
                    colliders=list(colliders), device=DEVICE, **kwargs, **config)
    return Simulator(objects, Particles(x=x, volume=volume, object_index=index, v=v), cfg,
                     n_batch=n_batch)


def slope_acceleration(track: np.ndarray, frame_dt: float, settle: float = 0.06) -> float:
    """Constant acceleration fitted to a 1D track (frames,) after ``settle`` seconds."""
    t = np.arange(len(track)) * frame_dt
    keep = t >= settle
    return float(2.0 * np.polyfit(t[keep], track[keep], 2)[0])


def falling_ball(family: str, params: dict, effects=(), dx: float = 0.02) -> Simulator:
    """A ball of one family thrown down and sideways onto a frictional ground (gradient checks)."""
    from mosiv_ros.sim import Gravity

    ball = sphere((0.2, 0.2, 0.14), 0.05, dx / 2)
    return scene([ball], [ObjectModel("ball", family, params)], dx=dx, lo=(0, 0, 0),
                 hi=(0.4, 0.4, 0.3), ground=Ground(height=0.08, friction=0.4),
                 effects=[Gravity(), *effects], velocities=[(0.5, 0.0, -1.0)])


def two_blocks(mu_a: float, mu_b: float, g) -> Simulator:
    """A block on a slab that a high-friction ground holds, under gravity ``g``."""
    from mosiv_ros.sim import Gravity

    dx = 0.02
    slab = box((0.35, 0.16, 0.12), (0.24, 0.06, 0.02), dx / 2)
    block = box((0.2, 0.16, 0.16), (0.05, 0.04, 0.02), dx / 2)
    return scene([slab, block],
                 [ObjectModel("slab", "elastic", {"E": 5e5, "friction": mu_a}),
                  ObjectModel("block", "elastic", {"E": 2e5, "friction": mu_b})],
                 dx=dx, lo=(0, 0, 0), hi=(0.7, 0.32, 0.3), ground=Ground(height=0.1, friction=2.0),
                 effects=[Gravity(g=g)])


def tilted_gravity(theta_deg: float) -> np.ndarray:
    """Gravity of a slope tilted by theta about y, downhill along +x."""
    theta = np.radians(theta_deg)
    return 9.81 * np.array([np.sin(theta), 0.0, -np.cos(theta)])
