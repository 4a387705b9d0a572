"""The warp-aggregated scatter and add (sim.warp_reduce) against plain sums.

On the CPU these are the plain atomics they replace; with ``MOSIV_TEST_DEVICE=cuda:0`` the same
checks exercise the warp shuffles: runs of equal keys, equal keys that are not neighbours, a
partial last warp, and lanes that skip the call (a divergent warp).
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from sim_scenes import DEVICE

from mosiv_ros.sim.runtime import load_modules
from mosiv_ros.sim.simulator import _momentum_and_mass, _slot_vectors
from mosiv_ros.sim.warp_reduce import add, clear_node, run_start, scatter

PLANE_Z = 4  # the test grid's node stride along a plane's first axis (``scatter``'s dims_z)


@wp.kernel
def _scatter_kernel(keys: wp.array(dtype=int), values: wp.array(dtype=float), skip: int,
                    grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    if i % wp.max(skip, 1) == 0 and skip > 0:  # (Warp evaluates both operands of ``and``)
        return  # these lanes leave the warp before the call
    key = keys[i]
    run = run_start(key)
    m = values[i]
    for plane in range(2):  # two planes of nine nodes per lane, as P2G's stencil has three
        for c in range(3):
            for e in range(3):
                j = c * 3 + e
                node = 2 * key + 2 * PLANE_Z * plane + PLANE_Z * c + e
                scatter(grid_m, grid_p, node, j, PLANE_Z, run, m * float(j + plane + 1),
                        wp.vec3(m, -2.0 * m, float(i + j)))


@wp.kernel
def _clear_kernel(grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    if i % 2 == 0:
        clear_node(grid_m, grid_p, i)


@wp.kernel
def _add_kernel(keys: wp.array(dtype=int), weights: wp.array(dtype=float), skip: int,
                target: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    if i % wp.max(skip, 1) == 0 and skip > 0:
        return
    key = keys[i]
    run = run_start(key)
    add(target, key, run, wp.vec3(1.0, 2.0, -1.0) * weights[i])


def _keys(n: int, rng: np.random.Generator) -> np.ndarray:
    """Runs of 1 to 9 equal keys, some keys coming back later (not neighbours)."""
    keys = np.repeat(rng.integers(0, 40, size=n), rng.integers(1, 10, size=n))[:n]
    return keys.astype(np.int32)


def _grids(nodes: int, interleaved: bool):
    """(slots or None, grid_m, grid_p): the simulator's one slot a node, or masses and momenta apart."""
    if interleaved:
        slots = wp.zeros(nodes, dtype=wp.vec4, device=DEVICE)
        grid_p, grid_m = _momentum_and_mass(slots, True)
        return slots, grid_m, grid_p
    return None, wp.zeros(nodes, dtype=float, device=DEVICE), wp.zeros(nodes, dtype=wp.vec3, device=DEVICE)


@pytest.mark.parametrize("interleaved", [False, True], ids=["apart", "interleaved"])
@pytest.mark.parametrize("n, skip", [(1000, 0), (77, 0), (1000, 3)])
def test_scatter_sums_what_every_lane_adds(n, skip, interleaved):
    """Two planes of nine nodes a lane, into masses and momenta apart and into one slot a node.

    Interleaved, a device of compute capability 9.0 or later adds each run's four sums with
    one vector reduction; the slot holds the momentum, then the mass.
    """
    load_modules(DEVICE, [__name__])
    rng = np.random.default_rng(n + skip)
    keys = _keys(n, rng)
    values = rng.normal(size=n).astype(np.float32)
    nodes = 2 * 39 + 4 * PLANE_Z + 3
    slots, grid_m, grid_p = _grids(nodes, interleaved)
    wp.launch(_scatter_kernel, dim=n, inputs=[wp.array(keys, dtype=int, device=DEVICE),
                                              wp.array(values, dtype=float, device=DEVICE), skip],
              outputs=[grid_m, grid_p], device=DEVICE)
    lanes = np.arange(n)
    kept = lanes % skip != 0 if skip else np.ones(n, dtype=bool)
    want_m, want_p = np.zeros(nodes), np.zeros((nodes, 3))
    for plane in range(2):
        for c in range(3):
            for e in range(3):
                j = 3 * c + e
                node = 2 * keys[kept] + 2 * PLANE_Z * plane + PLANE_Z * c + e
                np.add.at(want_m, node, values[kept] * (j + plane + 1))
                np.add.at(want_p, node, np.stack([values, -2 * values, lanes + j], axis=1)[kept])
    assert np.allclose(grid_m.numpy(), want_m, rtol=1e-5, atol=1e-4)
    assert np.allclose(grid_p.numpy(), want_p, rtol=1e-5, atol=1e-2)
    if interleaved:
        assert np.array_equal(slots.numpy(), np.concatenate([grid_p.numpy(), grid_m.numpy()[:, None]], axis=1))


@pytest.mark.parametrize("interleaved", [False, True], ids=["apart", "interleaved"])
def test_clear_node_zeroes_a_nodes_mass_and_momentum_in_either_layout(interleaved):
    """Interleaved, a device of compute capability 9.0 or later clears each slot with one store."""
    load_modules(DEVICE, [__name__])
    rng = np.random.default_rng(7)
    n = 300
    values = rng.normal(size=(n, 4)).astype(np.float32)
    slots, grid_m, grid_p = _grids(n, interleaved)
    grid_m.assign(values[:, 3])
    grid_p.assign(values[:, :3])
    wp.launch(_clear_kernel, dim=n, inputs=[grid_m, grid_p], device=DEVICE)
    want = values.copy()
    want[::2] = 0.0
    assert np.array_equal(grid_p.numpy(), want[:, :3])
    assert np.array_equal(grid_m.numpy(), want[:, 3])
    if interleaved:
        assert np.array_equal(slots.numpy(), want)


@pytest.mark.parametrize("slots", [False, True], ids=["vectors", "slots"])
@pytest.mark.parametrize("n, skip", [(1000, 0), (45, 0), (1000, 4)])
def test_add_sums_what_every_lane_adds(n, skip, slots):
    """Into an array of vectors, and into the first three floats of 16-byte slots (the grids' velocity
    gradients on a device of compute capability 9.0 or later, which adds them with one vector reduction).
    """
    load_modules(DEVICE, [__name__])
    rng = np.random.default_rng(n + skip)
    keys = _keys(n, rng)
    weights = rng.normal(size=n).astype(np.float32)
    start = rng.normal(size=(40, 4)).astype(np.float32)
    if slots:
        memory = wp.array(start, dtype=wp.vec4, device=DEVICE)
        target = _slot_vectors(memory)
    else:
        target = wp.array(start[:, :3], dtype=wp.vec3, device=DEVICE)
    want = start[:, :3].astype(np.float64)
    wp.launch(_add_kernel, dim=n, inputs=[wp.array(keys, dtype=int, device=DEVICE),
                                          wp.array(weights, dtype=float, device=DEVICE), skip, target],
              device=DEVICE)
    kept = np.arange(n) % skip != 0 if skip else np.ones(n, dtype=bool)
    np.add.at(want, keys[kept], weights[kept, None] * np.array([1.0, 2.0, -1.0]))
    assert np.allclose(target.numpy(), want, rtol=1e-5, atol=1e-4)
    if slots:
        assert np.array_equal(memory.numpy()[:, 3], start[:, 3])  # the slots' fourth floats are left as they were
