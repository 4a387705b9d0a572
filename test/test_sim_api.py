"""Simulator set-up, validation, divergence reporting, batching and continuation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import warp as wp
from sim_scenes import DEVICE, falling_ball, scene

from mosiv_ros.identify.losses import chamfer
from mosiv_ros.sim import (
    BodyForce,
    Collider,
    Effect,
    Gravity,
    Ground,
    KelvinVoigtDamping,
    LinearDrag,
    ObjectModel,
    ParameterError,
    ParamSpec,
    Particles,
    SimulationDiverged,
    Simulator,
    kernels,
)
from mosiv_ros.sim.effects import GridView
from mosiv_ros.sim.params import REPLICAS, lane_count, lane_particle, param
from mosiv_ros.sim.runtime import lock_file
from mosiv_ros.sim.sampling import box, sphere
from mosiv_ros.sim.simulator import GRAPH_SUBSTEPS, graph_runs


def test_out_of_range_parameter_is_refused_naming_object_parameter_and_range():
    with pytest.raises(ParameterError, match=r"nu of object 'ball' \(elastic\) = 0\.6 .*\[0, 0\.49\]"):
        falling_ball("elastic", {"nu": 0.6})
    sim = falling_ball("plastic", {})
    with pytest.raises(ParameterError, match=r"yield_stress of object 'ball' \(plastic\) = -5 Pa"):
        sim.params.set("yield_stress", -5.0)


def test_a_rows_check_names_the_first_value_out_of_range_and_skips_objects_whose_family_has_no_use_for_it():
    """``Parameters.validate`` checks every row as arrays: the first bad value in (row, object) order is named."""
    from mosiv_ros.sim.materials import MATERIAL_PARAMS
    from mosiv_ros.sim.params import Parameters

    params = Parameters(MATERIAL_PARAMS, 3, ["cube", "clay"], ["elastic", "plastic"], "cpu")
    params.validate()
    rows = params.get("yield_stress")
    rows[:, 0] = -1.0  # the elastic cube has no yield stress: any value of it passes
    params.set("yield_stress", rows)
    params.validate()
    values = params.get("E")
    values[2, 0], values[1, 1] = 1e12, np.nan  # row 1's clay comes first in index order
    params._host[params._slices["E"]] = values.ravel()  # as a caller writing the arrays would, unchecked
    with pytest.raises(ParameterError, match=r"E of object 'clay' \(plastic\), parameter set 1 = nan Pa"):
        params.validate()
    with pytest.raises(ParameterError, match=r"E of object 'cube' \(elastic\), parameter set 2 = 1e\+12 Pa"):
        params.set("E", np.where(np.isnan(values), 1e5, values))  # the same check on setting


def test_parameters_update_all_or_nothing_and_the_device_holds_what_the_host_reads():
    """Values are read on the host (``Parameters.get``): the device's copy must hold the same."""
    sim = falling_ball("plastic", {"E": 1e5})
    with pytest.raises(ParameterError, match="yield_stress"):
        sim.params.update({"E": 2e5, "yield_stress": -5.0})
    assert sim.params.get("E")[0, 0] == 1e5  # the refused update changed nothing
    sim.params.update({"E": 2e5, "nu": 0.25})
    sim.params.set("yield_stress", {"ball": 300.0})
    sim.params.replicate()
    for name in sim.params.specs:
        host = sim.params.get(name).astype(np.float32).ravel()
        assert np.array_equal(sim.params.arrays[name].numpy(), host), name
        assert np.array_equal(sim.params[name].numpy(), np.repeat(host, REPLICAS)), name
    assert (sim.params.get("E")[0, 0], sim.params.get("yield_stress")[0, 0]) == (2e5, 300.0)
    traj = sim.rollout(2, grad=True)
    grads = sim.backward(np.ones_like(traj))
    assert np.abs(grads.params["E"]).max() > 0
    for name, grad in grads.params.items():  # one copy from the device, as each name's own view holds
        assert np.array_equal(grad.ravel(), sim.params.arrays[name].grad.numpy()), name


def test_parameter_a_family_does_not_use_is_not_range_checked():
    sim = falling_ball("fluid", {"E": -1.0})  # a fluid has no Young's modulus
    assert sim.params.get("E")[0, 0] == -1.0


def test_unknown_family_parameter_and_object_are_refused_by_name():
    dx = 0.02
    ball = sphere((0.2, 0.2, 0.2), 0.05, dx / 2)
    with pytest.raises(ParameterError, match="unknown material family 'rubber'"):
        scene([ball], [ObjectModel("ball", "rubber")], dx=dx, lo=(0, 0, 0), hi=(0.4, 0.4, 0.4))
    with pytest.raises(ParameterError, match="unknown parameter.*youngs"):
        scene([ball], [ObjectModel("ball", "elastic", {"youngs": 1.0})], dx=dx, lo=(0, 0, 0),
              hi=(0.4, 0.4, 0.4))
    sim = falling_ball("elastic", {})
    with pytest.raises(ParameterError, match="unknown object 'cube'"):
        sim.params.set("E", {"cube": 1e5})


def test_particles_outside_the_domain_are_refused_naming_the_object():
    dx = 0.02
    with pytest.raises(ParameterError, match="object 'ball'.*enlarge the domain"):
        scene([sphere((0.05, 0.2, 0.2), 0.05, dx / 2)], [ObjectModel("ball", "elastic")],
              dx=dx, lo=(0, 0, 0), hi=(0.4, 0.4, 0.4))


def test_non_finite_initial_velocities_and_volumes_are_refused():
    sim = falling_ball("elastic", {"E": 3e4})
    v = np.zeros((sim.n_particles, 3))
    v[3, 1] = np.nan
    with pytest.raises(ParameterError, match="initial velocities must be finite"):
        sim.set_initial_velocity(v)
    with pytest.raises(ParameterError, match="volumes must be finite"):
        sim.set_volume(np.full(sim.n_particles, np.inf))
    sim.set_initial_velocity(np.ones(3))  # a finite one is taken, for every particle
    assert np.allclose(sim.initial_velocity()[0], 1.0)


@wp.kernel
def _anti_drag(m: wp.array(dtype=float), p: wp.array(dtype=wp.vec3),
               rate: wp.array(dtype=float), a: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    if m[i] > 0.0:
        wp.atomic_add(a, i, p[i] / m[i] * param(rate, 0, i))


class AntiDrag(Effect):
    """A runaway term (negative drag) plugged in through the extension point."""

    name = "anti_drag"
    params = (ParamSpec("rate", 0.0, 0.0, 1.0e4, "1/s", "growth rate"),)

    def accelerate(self, grid: GridView, values: dict) -> None:
        wp.launch(_anti_drag, dim=grid.n_batch * grid.n_objects * grid.n_nodes,
                  inputs=[grid.m, grid.p, values["rate"]], outputs=[grid.a], device=grid.device)


def test_a_diverging_run_stops_with_an_error_naming_object_and_frame_not_nans():
    sim = falling_ball("elastic", {"E": 3e4}, effects=(AntiDrag(rate=400.0),))
    sim.params.update({"anti_drag.rate": 0.0})
    sim.rollout(1, grad=True)
    sim.params.update({"anti_drag.rate": 400.0})
    with pytest.raises(SimulationDiverged) as raised:
        sim.rollout(20, grad=True)
    error = raised.value
    assert error.object_name == "ball" and 1 <= error.frame < 20
    assert "frame" in str(error) and "'ball'" in str(error)
    assert "exceeds one grid cell per substep" in error.reason or "non-finite" in error.reason
    with pytest.raises(RuntimeError, match="preceding rollout"):  # nothing left of either rollout
        sim.frame_state(0)


def test_extension_point_effect_parameters_live_in_the_parameter_table():
    sim = falling_ball("elastic", {}, effects=(AntiDrag(rate=2.0),))
    assert sim.params.get("anti_drag.rate")[0] == 2.0
    with pytest.raises(ParameterError, match="anti_drag.rate.*out of range"):
        sim.params.set("anti_drag.rate", -1.0)
    with pytest.raises(ParameterError, match="unknown parameter.*speed"):
        AntiDrag(speed=1.0)


class UniformPerObject(Effect):
    """Claims a per-object parameter as its uniform acceleration: not one vector per batch."""

    name = "uneven_wind"
    params = (ParamSpec("a", 0.0, -10.0, 10.0, "m/s^2", "acceleration", per_object=True),)
    uniform = "a"


def test_a_uniform_acceleration_must_be_one_vector_per_batch():
    with pytest.raises(ParameterError, match="'uneven_wind'.*one 3-vector per batch"):
        falling_ball("elastic", {}, effects=(UniformPerObject(),))


def test_batched_rollout_equals_one_rollout_per_parameter_set():
    sims = [falling_ball("elastic", {"E": e}) for e in (3e4, 9e4)]
    batched = falling_ball("elastic", {"E": 3e4})
    batched = scene([(batched.initial_positions(), batched.volumes()[0])],
                    batched.objects, dx=batched.dx, lo=batched.lo, hi=batched.hi,
                    ground=batched.config.ground, effects=batched.effects,
                    velocities=[(0.5, 0.0, -1.0)], n_batch=2)
    batched.params.set("E", [[3e4], [9e4]])
    substeps = max(s.time_step()[0] for s in sims)
    together = batched.rollout(5, substeps=substeps)
    for b, sim in enumerate(sims):
        # equal up to the order of float atomics (which a GPU does not fix)
        assert np.abs(together[:, b] - sim.rollout(5, substeps=substeps)[:, 0]).max() < 1e-6


@pytest.mark.parametrize("stiff", [4e5, 4.2e5])  # the stiffest row's substeps even (74), odd (75)
def test_rows_at_their_own_time_steps_move_as_each_alone_at_its_own(stiff):
    """``rollout(own_steps=True)``: a soft row waits out the stiff rows' extra substeps unchanged."""
    values = [(3e4, 5e4), (stiff, 5e4), (1e4, 2e5)]
    alone = [_two_balls() for _ in values]
    for sim, (ball, block) in zip(alone, values, strict=True):
        sim.params.set("E", [[ball, block]])
    together = _two_balls(n_batch=3)
    together.params.set("E", [list(v) for v in values])
    substeps, _ = together.own_time_steps()
    assert substeps.tolist() == [sim.time_step()[0] for sim in alone]
    assert len(set(substeps.tolist())) == 3
    moved = together.rollout(4, own_steps=True)
    for b, sim in enumerate(alone):
        assert _equal(moved[:, b], sim.rollout(4)[:, 0]), b
    # at the stiffest row's step the soft rows move otherwise (what own steps are for)
    assert not np.allclose(together.rollout(4)[:, 0], moved[:, 0], rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="own_steps=True takes no substeps"):
        together.rollout(2, own_steps=True, substeps=int(substeps.max()))
    finger = Collider("sphere", (0.03,), np.array([0.0, 1.0]), np.array([[0.45, 0.2, 0.3]] * 2))
    gripped = _two_balls(n_batch=2, colliders=[finger])
    assert not gripped.own_steps_allowed
    with pytest.raises(ParameterError, match="own time steps need a scene without colliders"):
        gripped.rollout(2, own_steps=True)


def _effects() -> list[Effect]:
    return [Gravity(), BodyForce(a=(0.5, 0.0, 0.0)), LinearDrag(), KelvinVoigtDamping()]


@pytest.mark.parametrize("effects", [None, _effects], ids=["no effects", "effects"])
def test_rows_at_their_own_time_steps_have_the_gradients_each_alone_has(effects):
    """``backward`` after ``rollout(own_steps=True, grad=True)``: each row's, as if it ran alone.

    With effects too: grid accelerations (a wind, a drag) and a stress (damping) per row.
    """
    values = [(3e4, 5e4), (4e5, 5e4), (1e4, 2e5)]
    together = _two_balls(n_batch=3, effects=effects and effects())
    together.params.set("E", [list(v) for v in values])
    together.params.set("nu", [[0.2, 0.3], [0.35, 0.25], [0.3, 0.2]])
    if effects:
        together.params.set("wind.a", [[0.5, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.5]])
        together.params.set("linear_drag.coefficient", [[1.0, 3.0], [2.0, 0.5], [0.0, 1.5]])
        together.params.set("damping.viscosity", [[0.5, 0.1], [0.0, 0.3], [0.2, 0.2]])
    assert len(set(together.own_time_steps()[0].tolist())) == 3
    frames, n = 4, together.n_particles
    dL = np.random.default_rng(5).normal(size=(frames + 1, 3, n, 3)) * 1e-2
    moved = together.rollout(frames, grad=True, own_steps=True)
    rows = together.backward(dL)
    for b in range(len(values)):
        sim = _two_balls(effects=effects and effects())
        for name in together.params.specs:
            sim.params.set(name, together.params.get(name)[b:b + 1])
        assert _equal(moved[:, b], sim.rollout(frames, grad=True)[:, 0]), b
        alone = sim.backward(dL[:, b:b + 1])
        # to rounding: a row's particles add their parameters' gradients on other replicas
        # (``params``) than alone, in another order
        for name, grad in alone.params.items():
            assert np.allclose(rows.params[name][b], grad[0], rtol=1e-4, atol=2e-5 * np.abs(grad).max()), (b, name)
        for got, expected in ((rows.v0[b], alone.v0[0]), (rows.volume[b], alone.volume[0])):
            assert np.allclose(got, expected, rtol=1e-4, atol=2e-5 * np.abs(expected).max()), b
    assert np.abs(rows.params["E"][0]).max() > 0 and np.abs(rows.params["nu"][2]).max() > 0
    if effects:
        assert all(np.abs(rows.params[name][1]).max() > 0
                   for name in ("wind.a", "linear_drag.coefficient", "damping.viscosity"))
    # at the stiffest row's step the soft rows' gradients are others (what own steps are for)
    together.rollout(frames, grad=True)
    common = together.backward(dL)
    assert not np.allclose(common.params["E"][0], rows.params["E"][0], rtol=1e-3, atol=0)


def test_batched_gradients_equal_one_backward_per_parameter_set():
    target = falling_ball("elastic", {"E": 6e4}).rollout(4)[:, 0].astype(np.float64)
    single = falling_ball("elastic", {"E": 3e4})
    batched = scene([(single.initial_positions(), single.volumes()[0])], single.objects,
                    dx=single.dx, lo=single.lo, hi=single.hi, ground=single.config.ground,
                    effects=single.effects, velocities=[(0.5, 0.0, -1.0)], n_batch=2)
    batched.params.set("E", [[3e4], [3e4]])
    substeps = single.time_step()[0]
    traj = single.rollout(4, grad=True, substeps=substeps)
    dL = np.zeros_like(traj, dtype=np.float64)
    dL[4, 0] = chamfer(traj[4, 0].astype(np.float64), target[4])[1]
    expected = single.backward(dL).params["E"][0, 0]
    batched.rollout(4, grad=True, substeps=substeps)
    both = batched.backward(np.repeat(dL, 2, axis=1)).params["E"]
    assert both[:, 0] == pytest.approx([expected, expected], rel=1e-5)


def test_a_rollout_continues_from_the_last_state():
    sim = falling_ball("elastic", {"E": 3e4})
    substeps = sim.time_step()[0]
    whole = sim.rollout(6, substeps=substeps)
    sim.rollout(3, substeps=substeps)
    rest = sim.rollout(3, substeps=substeps, initial=sim.last_state())
    assert np.abs(rest[3] - whole[6]).max() < 1e-6


def test_backward_needs_a_gradient_rollout_and_a_matching_seed():
    sim = falling_ball("elastic", {})
    with pytest.raises(RuntimeError, match="rollout"):
        sim.backward(np.zeros((2, 1, sim.n_particles, 3)))
    sim.rollout(2, grad=True)
    with pytest.raises(ValueError, match="shape"):
        sim.backward(np.zeros((5, 1, sim.n_particles, 3)))


def test_forcing_fewer_substeps_than_the_stability_bound_is_refused():
    sim = falling_ball("elastic", {"E": 3e4})
    n_sub, _ = sim.time_step()
    with pytest.raises(ParameterError, match="below the stability bound"):
        sim.rollout(1, substeps=n_sub - 1)


def test_stiffer_material_gets_more_substeps_per_frame():
    soft = scene([box((0.2, 0.2, 0.2), (0.03, 0.03, 0.03), 0.01)],
                 [ObjectModel("b", "elastic", {"E": 1e4})], dx=0.02, lo=(0, 0, 0),
                 hi=(0.4, 0.4, 0.4))
    hard = scene([box((0.2, 0.2, 0.2), (0.03, 0.03, 0.03), 0.01)],
                 [ObjectModel("b", "elastic", {"E": 1e7})], dx=0.02, lo=(0, 0, 0),
                 hi=(0.4, 0.4, 0.4))
    assert hard.time_step()[0] > 5 * soft.time_step()[0]


def test_the_time_step_follows_the_initial_velocities_each_row_its_own():
    """The CFL bound counts the fastest initial velocity, of each row, as last set."""
    sim = falling_ball("elastic", {"E": 3e4})
    given = sim.initial_velocity()
    n_given, dt_given = sim.time_step()
    fast = np.zeros((sim.n_particles, 3))
    fast[sim.n_particles // 2] = (0.0, 0.0, -40.0)  # one particle, downwards
    sim.set_initial_velocity(fast)
    n_fast, dt_fast = sim.time_step()
    assert n_fast > n_given
    assert dt_fast * (40.0 + sim.config.max_speed) <= sim.config.cfl * sim.dx
    sim.set_initial_velocity(given)
    assert sim.time_step() == (n_given, dt_given)
    rows = _two_balls(n_batch=2)
    v = np.zeros((2, rows.n_particles, 3))
    v[1, 0] = (40.0, 0.0, 0.0)
    rows.set_initial_velocity(v)
    substeps, _ = rows.own_time_steps()
    assert substeps[1] > substeps[0]
    assert rows.time_step()[0] == substeps[1]


def test_what_the_simulator_returns_is_a_copy_that_later_sets_leave_alone():
    sim = falling_ball("elastic", {"E": 3e4})
    v, volume, x = sim.initial_velocity(), sim.volumes(), sim.initial_positions()
    kept = v.copy(), volume.copy(), x.copy()
    sim.set_initial_velocity(v + 1.0)
    sim.set_volume(volume * 2.0)
    x += 1.0  # a caller's edit of what it got
    assert np.array_equal(v, kept[0]) and np.array_equal(volume, kept[1])
    assert np.array_equal(sim.initial_velocity(), kept[0] + 1.0)
    assert np.array_equal(sim.initial_positions(), kept[2])
    first = sim.rollout(1)
    again = sim.rollout(1)
    assert not np.shares_memory(first, again)


def test_one_scene_in_domains_of_different_margins_moves_the_same():
    """A floor on a layer of grid nodes acts alike whatever the (dx-snapped) domain corner."""
    from mosiv_ros.sim import Gravity, Ground, domain_around

    dx = 0.02
    ball = sphere((0.0, 0.0, 0.06), 0.04, dx / 2)
    tracks = []
    for margin in (0.1, 0.13, 0.45):  # floor nodes at z = 0.0, -1.5e-8 and 0.0 in float32
        lo, hi = domain_around(ball[0], dx, margin, floor=0.0)
        sim = scene([ball], [ObjectModel("ball", "elastic", {"E": 3e4})], dx=dx, lo=lo, hi=hi,
                    ground=Ground(height=0.0, friction=0.4), effects=[Gravity()],
                    velocities=[(0.3, 0.0, -1.0)])
        tracks.append(sim.rollout(8)[:, 0])
    for other in tracks[1:]:
        assert np.abs(other - tracks[0]).max() < 1e-4


def test_grid_passes_run_over_a_box_holding_every_node_the_particles_reach():
    """On the CPU the grid passes skip the empty grid; no node a particle reaches falls outside."""
    from mosiv_ros.sim.simulator import SimState, _Grid, _State

    dx = 0.02
    ball = sphere((0.12, 0.2, 0.2), 0.04, dx / 2)
    block = box((0.27, 0.2, 0.2), (0.04, 0.04, 0.04), dx / 2)
    sim = scene([ball, block], [ObjectModel("ball", "elastic", {"E": 3e4}),
                                ObjectModel("block", "plastic", {"E": 5e4})],
                dx=dx, lo=(0, 0, 0), hi=(0.6, 0.4, 0.4), ground=Ground(height=0.05),
                velocities=[(1.0, 0.0, -0.5), (-1.0, 0.0, 0.0)], n_batch=2)
    n_sub, dt = sim.time_step()
    x = np.repeat(sim.initial_positions()[None], 2, axis=0).astype(np.float64)
    lying = x.copy()
    lying[1, :3] = [[0.061, 0.061, 0.061], [0.539, 0.339, 0.339], [0.3, 0.07, 0.33]]  # near walls
    for positions in (x, lying):
        src, dst = _State(2 * sim.n_particles, sim.device, False), _State(2 * sim.n_particles,
                                                                          sim.device, False)
        sim._assign_state(src, SimState.rest(positions, np.array([0.5, -0.3, 0.2])))
        grid = _Grid(2, 2, sim.dims, 2 * sim.n_particles, False, sim.device, False)
        sim._replicate()
        sim._collider_poses(0, n_sub, dt)
        sim._set_steps(dt, n_sub)
        sim._substep(src, dst, grid, 0)
        box_lo, box_dims = sim._active_box(src)
        ijk = np.stack(np.unravel_index(np.arange(sim.n_nodes), sim.dims), axis=1)
        inside = np.all((ijk >= box_lo) & (ijk < np.add(box_lo, box_dims)), axis=1)
        m = grid.m.numpy().reshape(2, 2, sim.n_nodes)
        v = np.abs(grid.v.numpy()).reshape(2, 2, sim.n_nodes, 3).max(axis=-1)
        assert np.all(m[..., ~inside] == 0.0)
        assert np.all((v > 0) <= (m > 0)) and np.count_nonzero(v) > 0.5 * np.count_nonzero(m)
        if DEVICE == "cpu":
            assert inside.sum() < (0.5 if positions is x else 1.0) * sim.n_nodes


@pytest.mark.skipif(not DEVICE.startswith("cuda"),
                    reason="CUDA graphs need a GPU: run with MOSIV_TEST_DEVICE=cuda:0")
def test_cuda_graph_replays_give_the_rollouts_and_gradients_of_single_launches():
    # a finger pushing a block: the collider's poses change every frame, so a graph that kept
    # the poses of the frame it was captured in would push from the wrong place; and the block's
    # stiffness changes between rollouts, as a fit's does, so that frames of 42 and 54 substeps
    # share the graphs of their first 32 (``graph_runs``), each run at its own dt
    dx, floor = 0.02, 0.1
    finger = Collider("sphere", (0.04,), np.array([0.0, 0.5]),
                      np.array([[0.1, 0.2, floor + 0.03], [0.6, 0.2, floor + 0.03]]), friction=0.5)
    moduli = (1e5, 1e5, 2e5, 2e5, 1e5)  # graphs: captured on a key's first run (after its kind's first), replayed after
    results = {}
    for graphs in (False, True):
        sim = scene([box((0.25, 0.2, floor + 0.03), (0.03, 0.03, 0.03), dx / 2)],
                    [ObjectModel("block", "elastic", {"E": 1e5})], dx=dx, lo=(0, 0, 0),
                    hi=(0.8, 0.4, 0.3), colliders=[finger], ground=Ground(height=floor),
                    cuda_graphs=graphs)
        results[graphs] = []
        for E in moduli:
            sim.params.set("E", E)
            plain = sim.rollout(8)
            traj = sim.rollout(8, grad=True)
            dL = np.zeros_like(traj, dtype=np.float64)
            dL[1:, 0, :, 0] = 1.0  # d(sum of x over frames)
            grads = sim.backward(dL)
            results[graphs].append((sim.time_step()[0], plain, traj, grads.params["E"][0, 0], grads.v0))
        assert bool(sim._graphs) == graphs
    assert [r[0] for r in results[True]] == [42, 42, 54, 54, 42]
    shared = {("kept", 0, 32), ("adjoint", 0, 32), ("frame", 0, 32, 0)}
    assert shared | {("kept", 32, 8), ("kept", 32, 16)} <= set(sim._graphs)
    assert results[False][0][2][-1, 0, :, 0].mean() > 0.27  # the finger reached and pushed the block
    for eager, graph in zip(results[False], results[True], strict=True):
        assert np.abs(graph[1] - eager[1]).max() < 1e-5 and np.abs(graph[2] - eager[2]).max() < 1e-5
        assert graph[3] == pytest.approx(eager[3], rel=1e-3)
        assert np.abs(graph[4] - eager[4]).max() < 1e-3 * np.abs(eager[4]).max()
    assert np.abs(results[True][2][2] - results[True][0][2]).max() > 1e-4  # the stiffer block moved otherwise


def test_graph_runs_cover_a_frame_in_runs_that_frames_of_other_lengths_share():
    runs = {n: graph_runs(n) for n in range(1, 400)}
    for n, frame in runs.items():
        assert [first for first, _ in frame] == [0, *np.cumsum([size for _, size in frame])[:-1]]
        assert sum(size for _, size in frame) == n
        assert all(size <= GRAPH_SUBSTEPS and size & (size - 1) == 0 and first % size == 0 for first, size in frame)
    assert graph_runs(100) == [(0, 32), (32, 32), (64, 32), (96, 4)]
    assert graph_runs(54) == [(0, 32), (32, 16), (48, 4), (52, 2)]


def _ball_and_block() -> tuple[float, float, list, list[ObjectModel]]:
    """dx, the floor's height, and an elastic ball beside a plastic block on it at spacing dx / 2."""
    dx, floor = 0.02, 0.1
    solids = [sphere((0.2, 0.2, floor + 0.06), 0.04, dx / 2), box((0.3, 0.2, floor + 0.04),
                                                                   (0.03, 0.04, 0.03), dx / 2)]
    return dx, floor, solids, [ObjectModel("ball", "elastic", {"E": 3e4}), ObjectModel("block", "plastic", {})]


def test_cell_order_is_invisible_to_callers():
    # Two objects, two batches, per-particle velocities and volumes that differ by particle, given
    # with the particles and through the setters: the simulator sorted by cell must give, in the
    # callers' order, what the unsorted one gives (up to the order of float sums), and its last
    # state must continue the same way.
    dx, floor, solids, objects = _ball_and_block()
    runs = {}
    for order in (False, True):
        config = scene(solids, objects, dx=dx, lo=(0, 0, 0), hi=(0.5, 0.4, 0.3),
                       ground=Ground(height=floor), cell_order=order).config
        x = np.concatenate([s[0] for s in solids])
        n = len(x)
        given_v = np.random.default_rng(1).normal(scale=0.3, size=(n, 3))
        given_volume = (dx / 2) ** 3 * np.random.default_rng(2).uniform(0.5, 1.5, size=n)
        sim = Simulator(objects, Particles(x=x, volume=given_volume, v=given_v,
                                           object_index=np.repeat([0, 1], [len(s[0]) for s in solids])),
                        config, n_batch=2)
        assert np.array_equal(sim.initial_velocity(), np.broadcast_to(given_v.astype(np.float32), (2, n, 3)))
        assert np.array_equal(sim.volumes(), np.broadcast_to(given_volume.astype(np.float32), (2, n)))
        v = np.random.default_rng(3).normal(scale=0.3, size=(2, n, 3))
        volume = (dx / 2) ** 3 * np.random.default_rng(4).uniform(0.5, 1.5, size=(2, n))
        sim.set_initial_velocity(v)
        sim.set_volume(volume)
        assert np.array_equal(sim.initial_velocity(), v.astype(np.float32))
        assert np.array_equal(sim.volumes(), volume.astype(np.float32))
        assert np.array_equal(sim.initial_positions(), np.concatenate([s[0] for s in solids]).astype(np.float32))
        assert np.array_equal(sim.object_index(), np.repeat([0, 1], [len(s[0]) for s in solids]))
        traj = sim.rollout(4, grad=True)
        dL = np.random.default_rng(5).normal(size=traj.shape)
        grads = sim.backward(dL)
        state = sim.frame_state(2)
        more = sim.rollout(2, initial=sim.last_state())
        runs[order] = traj, grads, state, more, sim._order
    (traj0, g0, s0, m0, o0), (traj1, g1, s1, m1, o1) = runs[False], runs[True]
    assert o0 is None and not np.array_equal(o1, np.arange(len(o1)))  # the order did change
    assert np.abs(traj1 - traj0).max() < 1e-6
    assert np.abs(m1 - m0).max() < 1e-6
    for a, b in zip((s0.x, s0.v, s0.C, s0.b), (s1.x, s1.v, s1.C, s1.b), strict=True):
        assert np.abs(b - a).max() < 1e-4 * max(1.0, np.abs(a).max())
    assert np.abs(g1.v0 - g0.v0).max() < 1e-4 * np.abs(g0.v0).max()
    assert np.abs(g1.volume - g0.volume).max() < 1e-4 * np.abs(g0.volume).max()
    for name in ("E", "nu", "yield_stress", "density", "friction"):
        assert g1.params[name] == pytest.approx(g0.params[name], rel=1e-3, abs=1e-9), name


@pytest.mark.parametrize("order", [False, True])
def test_a_queued_rollout_and_a_gradient_on_the_device_give_what_the_host_gets(order):
    # The fit's loss on a GPU reads a queued rollout's positions where they are and hands dL/dx
    # back there (identify.fit). Sorted by cell, both pass through the callers' order.
    dx, floor, solids, objects = _ball_and_block()
    sim = scene(solids, objects, dx=dx, lo=(0, 0, 0), hi=(0.5, 0.4, 0.3), ground=Ground(height=floor),
                velocities=[(0.5, 0.0, -1.0), (0.0, 0.0, 0.0)], n_batch=2, cell_order=order)
    assert (sim._order is not None) == order
    traj = sim.rollout(4, grad=True)
    dL = np.random.default_rng(5).normal(size=traj.shape).astype(np.float32)
    expected = sim.backward(dL)
    queued = sim.queue_rollout(4, grad=True)
    queued.wait()
    exact = DEVICE == "cpu"  # on a GPU float atomics add in no fixed order
    positions = queued.positions.numpy().reshape(traj.shape)
    assert np.array_equal(positions, traj) if exact else np.abs(positions - traj).max() < 1e-6
    got = sim.backward(wp.array(dL.reshape(-1, 3), dtype=wp.vec3, device=sim.device))
    for a, b in ((got.v0, expected.v0), (got.volume, expected.volume),
                 *((got.params[name], expected.params[name]) for name in ("E", "nu", "yield_stress"))):
        np.testing.assert_allclose(a, b, rtol=0 if exact else 1e-4, atol=0 if exact else 1e-6 * np.abs(b).max())
    stale = sim.queue_rollout(2, grad=True)
    sim.rollout(2, grad=True)
    with pytest.raises(RuntimeError, match="next rollout"):
        stale.wait()
    with pytest.raises(ValueError, match="wp.vec3"):
        sim.backward(wp.zeros(5, dtype=wp.vec3, device=sim.device))


def test_the_check_of_several_frames_names_the_first_frame_row_and_object_at_fault():
    """``Simulator._diverged`` over a queued rollout's frames at once (what ``wait`` reads on a GPU).

    Statistics per frame, row and object: fastest speed, non-finite count, count outside the
    domain, smallest det b. The first failure in (frame, row, object) order is named, each
    row's speed against one cell per its own substep.
    """
    dx = 0.02
    sim = scene([box((0.1, 0.1, 0.1), (0.02,) * 3, dx / 2), box((0.2, 0.1, 0.1), (0.02,) * 3, dx / 2)],
                [ObjectModel("a", "elastic", {}), ObjectModel("b", "plastic", {})],
                dx=dx, lo=(0, 0, 0), hi=(0.3, 0.2, 0.2), n_batch=2)
    stats = np.tile(np.float32([0.1, 0.0, 0.0, 1.0]), (3, 2, 2, 1))  # frames, rows, objects, statistics
    stats[1, 1, 0, 3] = 1e-7  # row 1, object a: inverted
    stats[1, 0, 1, 2] = 3  # row 0, object b: outside, earlier in that order
    stats[2, 0, 0, 1] = 2  # a frame later: non-finite
    with pytest.raises(SimulationDiverged) as raised:
        sim._diverged(stats.reshape(3, -1), 5, 1e-3)
    assert (raised.value.frame, raised.value.batch, raised.value.object_name) == (6, 0, "b")
    assert "3 particle(s) left the simulation domain" in raised.value.reason
    stats[1, 0, 1, 2] = 0
    with pytest.raises(SimulationDiverged, match=r"frame 6: object 'a' \(parameter set 1\): the deformation inverted"):
        sim._diverged(stats.reshape(3, -1), 5, 1e-3)
    stats[1, 1, 0, 3] = 1.0
    stats[0, :, 1, 0] = 50.0  # 50 m/s: over one cell a substep of 1e-3 s (20 m/s), not of 1e-4 s (200)
    with pytest.raises(SimulationDiverged, match=r"frame 5: object 'b' \(parameter set 1\): speed 50 m/s exceeds"):
        sim._diverged(stats.reshape(3, -1), 5, np.array([1e-4, 1e-3]))
    stats[0, :, 1, 0] = 0.1
    with pytest.raises(SimulationDiverged, match=r"frame 7: object 'a' \(parameter set 0\): 2 particle"):
        sim._diverged(stats.reshape(3, -1), 5, 1e-3)
    stats[2, 0, 0, 1] = 0
    sim._diverged(stats.reshape(3, -1), 5, 1e-3)  # nothing at fault
    sim._diverged(stats[0].ravel(), 5, 1e-3)  # one frame, as a frame checked at once


def test_a_queued_rollout_that_diverges_says_so_by_its_wait_at_the_latest():
    sim = falling_ball("elastic", {"E": 3e4}, effects=(AntiDrag(rate=400.0),))
    with pytest.raises(SimulationDiverged) as raised:
        sim.queue_rollout(20, grad=True).wait()
    assert raised.value.object_name == "ball"
    with pytest.raises(RuntimeError, match="preceding rollout"):
        sim.backward(np.zeros((21, 1, sim.n_particles, 3)))


def test_the_default_sorts_short_lines_and_scattered_particles_and_keeps_long_lines():
    from mosiv_ros.sim.simulator import SORT_LINES, cell_lines

    dx = 0.02
    lattices = {}
    for name, half in (("long", (0.03, 0.03, 0.2)), ("short", (0.05, 0.04, 0.03))):
        sim = scene([box((0.2, 0.2, 0.3), half, dx / 2)], [ObjectModel("block", "elastic", {})],
                    dx=dx, lo=(0, 0, 0), hi=(0.4, 0.4, 0.6))
        lattices[name] = sim._stencil_cells(sim.initial_positions())
        # on the CPU nothing is sorted by default, on a GPU the short lines
        assert (sim._order is None) == (DEVICE == "cpu" or name == "long")
    # two particles to a cell along z, lines as long as the block: 40 and 6 particles
    assert cell_lines(lattices["long"]) == pytest.approx(40, rel=0.05) and SORT_LINES <= 40
    assert cell_lines(lattices["short"]) == pytest.approx(6, rel=0.05) and SORT_LINES > 6
    shuffled = lattices["long"][np.random.default_rng(0).permutation(len(lattices["long"]))]
    assert cell_lines(shuffled) < 1.2
    # sorted, a line holds every particle of its column of cells: 8 a cell, 20 cells along z
    assert cell_lines(np.sort(shuffled)) == pytest.approx(160, rel=0.05)


def test_kernel_arguments_are_found_by_name_and_a_missing_or_unused_one_is_named():
    from mosiv_ros.sim import kernels
    from mosiv_ros.sim.simulator import _bind, _Grid, _State

    sim = falling_ball("elastic", {})
    n = sim.n_particles
    src, dst = _State(n, sim.device, False), _State(n, sim.device, False)
    grid = _Grid(1, 1, sim.dims, n, False, sim.device, False)
    args = dict(zip([a.label for a in kernels.g2p.adj.args],
                    _bind(kernels.g2p, {"src": src, "dst": dst, "grid": grid, "own": sim._steps, "substep": 0},
                          sim._scene), strict=True))
    assert args["src_x"] is src.x and args["dst_x"] is dst.x and args["dst_C"] is dst.C
    assert args["grid_v"] is grid.v and args["ground_height"] is sim.params["ground.height"]
    assert args["own_dt"] is sim._steps.dt and args["n_particles"] == n and args["has_ground"] == 1
    with pytest.raises(TypeError, match=r"kernel g2p: no value for its parameter 'dst_x'"):
        _bind(kernels.g2p, {"src": src, "grid": grid, "own": sim._steps, "substep": 0}, sim._scene)
    with pytest.raises(TypeError, match=r"kernel g2p takes nothing from collider"):
        _bind(kernels.g2p, {"src": src, "dst": dst, "grid": grid, "own": sim._steps, "substep": 0,
                            "collider": sim._colliders}, sim._scene)


def _two_balls(n_batch=1, effects=None, **config):
    dx = 0.02
    ball = sphere((0.12, 0.2, 0.2), 0.04, dx / 2)
    block = box((0.27, 0.2, 0.2), (0.04, 0.04, 0.04), dx / 2)
    return scene([ball, block], [ObjectModel("ball", "elastic", {"E": 3e4}),
                                 ObjectModel("block", "plastic", {"E": 5e4})],
                 dx=dx, lo=(0, 0, 0), hi=(0.6, 0.4, 0.4), ground=Ground(height=0.05),
                 velocities=[(1.0, 0.0, -0.5), (-1.0, 0.0, 0.0)], n_batch=n_batch, effects=effects,
                 **config)


def test_a_scene_without_colliders_updates_its_grid_as_the_kernel_with_their_code_does():
    """The grid update without the colliders' code against the one with it on a substep's grid.

    Velocities and adjoints of a two-object contact on the ground near the walls, two parameter sets.
    """
    from mosiv_ros.sim.simulator import _GRID_UPDATE_ADJOINTS, SimState, _bind, _Grid, _State

    sim = _two_balls(n_batch=2)
    assert sim._grid_update is kernels.grid_update_kernels(0, 2)[0]
    assert _two_balls(colliders=[Collider("sphere", (0.03,), np.array([0.0, 1.0]), np.array([[0.45, 0.2, 0.3]] * 2))
                                 ])._grid_update is kernels.grid_update_kernels(kernels.MAX_COLLIDERS, 2)[0]
    n_sub, dt = sim.time_step()
    total = 2 * sim.n_particles
    x = np.repeat(sim.initial_positions()[None], 2, axis=0).astype(np.float64)
    ball = sim.object_index() == 0
    x[1, ball] += [0.06, 0.0, 0.0]  # the second row's ball against the block
    v = np.where(ball[None, :, None], [1.0, 0.0, -0.5], [-1.0, 0.0, 0.0])
    src, dst = _State(total, sim.device, False), _State(total, sim.device, False)
    sim._assign_state(src, SimState.rest(x, v))
    grids = [_Grid(2, 2, sim.dims, total, False, sim.device, True) for _ in range(2)]
    sim._replicate()
    sim._set_steps(dt, n_sub)
    sim._substep(src, dst, grids[0], 0)  # P2G and the grid update without colliders
    for a, b in zip(grids[1].arrays, grids[0].arrays, strict=True):
        wp.copy(a, b)
    box_lo, box_dims = sim._active_box(src)
    seed = np.random.default_rng(2).normal(size=(len(grids[0].v), 3)).astype(np.float32)
    velocities, adjoints = [], []
    for colliders, grid in zip((0, kernels.MAX_COLLIDERS), grids, strict=True):
        kernel, adjoint = kernels.grid_update_kernels(colliders, 2)
        grid.v.zero_()
        args = _bind(kernel, {"grid": grid, "collider": sim._colliders, "substep": 0, "box_lo": wp.vec3i(*box_lo),
                              "box_dims": wp.vec3i(*box_dims), "own": sim._steps}, sim._scene)
        wp.launch(kernel, int(np.prod(box_dims)) * 2 * 2, device=sim.device, inputs=args)
        grid.v.grad.assign(seed)
        labels = [arg.label for arg in kernel.adj.args]
        wp.launch(adjoint, int(np.prod(box_dims)) * 2 * 2, device=sim.device,
                  inputs=[*args, *(args[labels.index(name)].grad for name in _GRID_UPDATE_ADJOINTS)])
        velocities.append(grid.v.numpy())
        adjoints.append([a.grad.numpy() for a in (grid.m, grid.p)])
    assert np.count_nonzero(np.abs(velocities[0]).max(axis=1)) > 100
    assert _equal(velocities[0], velocities[1])
    for free, general in zip(*adjoints, strict=True):
        assert np.abs(free).max() > 0 and _equal(free, general)


def test_a_grid_reused_after_a_substep_elsewhere_holds_what_a_fresh_grid_holds():
    """Grids are cleared over the box the last substep wrote: nothing of it may remain."""
    from mosiv_ros.sim.simulator import SimState, _Grid, _State

    # the drag writes the effects' accelerations (gravity, being uniform, writes none)
    sim = _two_balls(n_batch=2, effects=[Gravity(), LinearDrag(coefficient=2.0)])
    n_sub, dt = sim.time_step()
    x = np.repeat(sim.initial_positions()[None], 2, axis=0).astype(np.float64)
    elsewhere = x + np.array([0.15, 0.08, -0.1])  # another box of nodes
    grids = [_Grid(2, 2, sim.dims, 2 * sim.n_particles, False, sim.device, False) for _ in range(2)]
    sim._replicate()
    sim._collider_poses(0, n_sub, dt)
    sim._set_steps(dt, n_sub)
    for grid, starts in zip(grids, ([x], [elsewhere, x]), strict=True):
        for positions in starts:
            src, dst = (_State(2 * sim.n_particles, sim.device, False) for _ in range(2))
            sim._assign_state(src, SimState.rest(positions, np.array([0.5, -0.3, 0.2])))
            sim._substep(src, dst, grid, 0)
    for name in ("m", "p", "a", "v"):
        fresh, reused = (getattr(g, name).numpy() for g in grids)
        assert np.count_nonzero(fresh) > 0 and _equal(fresh, reused), name


def test_gradients_after_an_earlier_backward_elsewhere_equal_a_fresh_simulators():
    """The tape's grids keep their gradients only over the box each substep wrote, zeroed per frame."""
    fresh, reused = _two_balls(), _two_balls()
    reused.rollout(3, grad=True)  # the balls move: later frames run over other boxes
    reused.backward(np.ones((4, 1, reused.n_particles, 3), np.float32))
    start = reused.frame_state(3)
    results = []
    for sim in (fresh, reused):
        traj = sim.rollout(2, grad=True, initial=start)
        results.append(sim.backward(np.random.default_rng(0).normal(size=traj.shape).astype(np.float32)))
    for name in ("E", "nu", "friction", "ground.friction", "gravity.g"):
        assert _equal(results[0].params[name], results[1].params[name]), name
    assert _equal(results[0].v0, results[1].v0)
    assert np.abs(results[0].params["E"]).max() > 0


@pytest.mark.skipif(DEVICE == "cpu", reason="tapes are kept on a CUDA device: run with MOSIV_TEST_DEVICE=cuda:0")
def test_tapes_kept_from_the_rollout_give_the_gradients_of_recomputed_frames():
    """``SimConfig.tape_memory``: frames kept by the rollout, or recomputed by the backward."""
    finger = Collider("sphere", (0.03,), np.array([0.0, 0.2]),
                      np.array([[0.05, 0.2, 0.2], [0.35, 0.2, 0.2]]), friction=0.5)
    sims = {memory: _two_balls(n_batch=2, colliders=[finger], tape_memory=memory) for memory in (0.0, 1.0)}
    rng = np.random.default_rng(1)
    results = {memory: [] for memory in sims}
    substeps = []
    # windows as a fit runs them: from the start, from a later state (another clock), longer,
    # stiffer (more substeps), and back (the substeps of before): each window's backward, the
    # last one's twice
    for frames, start, stiffness in ((4, 0, 3e4), (3, 2, 3e4), (6, 0, 3e4), (4, 0, 1e5), (4, 0, 3e4)):
        seed = None
        for memory, sim in sims.items():
            sim.params.set("E", {"ball": stiffness})
            initial = sim.frame_state(start) if start else None
            traj = sim.rollout(frames, grad=True, initial=initial, start_frame=start)
            assert (sim.kept_tape_frames >= frames) == (memory > 0)
            seed = rng.normal(size=traj.shape).astype(np.float32) if seed is None else seed
            results[memory].append((traj, sim.backward(seed), sim.frame_state(frames).x))
        substeps.append(sims[0.0].time_step()[0])
    for memory, sim in sims.items():  # a second backward of one rollout recomputes its frames
        results[memory].append((None, sim.backward(seed), None))
    assert substeps[3] > substeps[2] == substeps[4]
    for recomputed, kept in zip(results[0.0], results[1.0], strict=True):
        if recomputed[0] is not None:
            assert np.abs(recomputed[0] - kept[0]).max() < 1e-5
            assert np.abs(recomputed[2] - kept[2]).max() < 1e-5
        # float atomics add in no fixed order on a GPU: equal to rounding, amplified by contact
        for name in ("E", "nu", "yield_stress", "friction", "ground.friction", "gravity.g"):
            assert np.allclose(recomputed[1].params[name], kept[1].params[name], rtol=1e-3,
                               atol=1e-4 * np.abs(recomputed[1].params[name]).max()), name
        for field in ("v0", "volume"):
            a, b = getattr(recomputed[1], field), getattr(kept[1], field)
            assert np.abs(a - b).max() < 1e-3 * np.abs(a).max(), field
    assert np.allclose(results[1.0][-1][1].params["E"], results[1.0][-2][1].params["E"], rtol=1e-3)
    assert np.abs(results[1.0][-1][1].params["E"]).min() > 0
    # a rollout that does not fit frees the kept frames and recomputes
    sims[1.0].config.tape_memory = 1e-6
    sims[1.0].rollout(2, grad=True)
    assert sims[1.0].kept_tape_frames == 0


@pytest.mark.parametrize("block_warps", [1, 2, 4])
def test_particles_spread_over_more_thread_blocks_move_and_differentiate_as_packed(block_warps):
    """``Simulator._spread``: P2G and G2P with fewer warps of particles a block run every particle once."""
    packed, spread = _two_balls(n_batch=2), _two_balls(n_batch=2)
    spread._spread(block_warps)
    results = []
    for sim in (packed, spread):
        traj = sim.rollout(3, grad=True)
        seed = np.random.default_rng(2).normal(size=traj.shape).astype(np.float32)
        results.append((traj, sim.backward(seed), sim.rollout(3)))
    assert _equal(results[0][0], results[1][0]) and _equal(results[0][2], results[1][2])
    assert np.abs(results[0][0][-1] - results[0][0][0]).max() > 0.02  # they moved
    for name in ("E", "nu", "yield_stress", "friction", "ground.friction"):
        assert _equal(results[0][1].params[name], results[1][1].params[name]), name
    assert _equal(results[0][1].v0, results[1][1].v0)
    assert np.abs(results[0][1].params["friction"]).max() > 0  # they touched


@pytest.mark.parametrize("block_warps", [1, 8])
def test_a_stencil_split_over_three_threads_moves_and_differentiates_as_one_thread(block_warps):
    """``kernels._p2g(3)``: each of a particle's three threads scatters one plane of its stencil.

    The grid's sums add in another order (so to rounding, amplified by the contact), and each
    particle's state and gradients are written and read once, not three times.
    """
    whole, split = _two_balls(n_batch=2), _two_balls(n_batch=2)
    whole._spread(block_warps)
    split._spread(block_warps, planes=3)
    results = []
    for sim in (whole, split):
        traj = sim.rollout(3, grad=True)
        seed = np.random.default_rng(2).normal(size=traj.shape).astype(np.float32)
        results.append((traj, sim.backward(seed)))
    (traj_whole, grads_whole), (traj_split, grads_split) = results
    assert np.abs(traj_whole[-1] - traj_whole[0]).max() > 0.02  # they moved
    assert np.abs(traj_split - traj_whole).max() < 1e-5
    for name in ("E", "nu", "yield_stress", "friction"):  # the balls touch each other, not the ground
        a, b = grads_whole.params[name], grads_split.params[name]
        assert np.abs(a).max() > 0, name
        assert np.allclose(b, a, rtol=1e-3, atol=1e-4 * np.abs(a).max()), name
    for field in ("v0", "volume"):
        a, b = getattr(grads_whole, field), getattr(grads_split, field)
        assert np.abs(b - a).max() < 1e-3 * np.abs(a).max(), field


def test_a_gpu_spreads_particles_over_at_least_spread_blocks_where_it_has_the_warps():
    from mosiv_ros.sim.simulator import SPREAD_BLOCKS, _block_warps

    for n in (1, 3121, 6242, 10_000, 33_000, 100_000, 1_000_000):
        warps = _block_warps(n)
        blocks, halved = -(-n // (32 * warps)), -(-n // (64 * warps))
        assert warps in (1, 2, 4, 8)
        assert blocks >= SPREAD_BLOCKS or warps == 1  # as many blocks as asked, if there are the warps
        assert warps == 8 or halved < SPREAD_BLOCKS  # and no fewer warps a block than needed
    assert _block_warps(3121) == 1 and _block_warps(100_000) == 8


def test_a_gpu_splits_p2g_over_three_threads_a_particle_where_their_blocks_fit_in_one_wave():
    from mosiv_ros.sim.simulator import SPREAD_BLOCKS, _block_warps, _p2g_planes

    for n in (1, 300, 3554, 6000, 10_662, 10_900, 11_000, 100_000, 1_000_000):
        planes, warps = _p2g_planes(n)
        blocks = -(-n // (32 * warps))
        if planes == 3:
            assert 3 * blocks <= SPREAD_BLOCKS  # one wave of the adjoint's one block a multiprocessor
            assert warps == 1 or 3 * -(-n // (16 * warps)) > SPREAD_BLOCKS  # no more warps a block than needed
        else:
            assert planes == 1 and warps == _block_warps(n) and 3 * -(-n // 256) > SPREAD_BLOCKS
    assert _p2g_planes(3554) == (3, 4) and _p2g_planes(100_000) == (1, 8)


def _equal(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal to the bit on the CPU; on a GPU, whose float atomics add in no fixed order, to rounding.

    On an H100 twelve backward passes of one rollout of ``_two_balls`` spread by up to 4e-6 of a
    gradient's largest entry (the nu gradient's smaller entry by 1e-4 of itself), so the GPU's
    bound is 2e-5 of it.
    """
    if DEVICE == "cpu":
        return np.array_equal(a, b)
    return np.allclose(a, b, rtol=1e-4, atol=2e-5 * np.abs(a).max())


@wp.kernel
def _lane_particles(part: int, parts: int, out: wp.array(dtype=int)):
    out[wp.tid()] = lane_particle(wp.tid(), part, parts)


@pytest.mark.skipif(not wp.is_cpu_available(), reason="the parts are the CPU's: this Warp has no CPU compiler")
@pytest.mark.parametrize("total", [1, 127, 128, 300, 3121])
def test_the_parts_of_a_launch_run_every_particle_once_on_replicas_of_their_own(total):
    # P2G's adjoint runs in parts side by side on the CPU: together they cover every particle
    # once, each in order, and no two parts add to one replica (particle i's is i % REPLICAS)
    for parts in (1, 2):
        runs = []
        for part in range(parts):
            out = wp.zeros(lane_count(total, part, parts), dtype=int, device="cpu")
            wp.launch(_lane_particles, dim=len(out), inputs=[part, parts], outputs=[out], device="cpu")
            runs.append(out.numpy())
        assert sorted(np.concatenate(runs).tolist()) == list(range(total))
        assert all(np.all(np.diff(run) > 0) for run in runs)
        lanes = [set((run % REPLICAS).tolist()) for run in runs]
        assert all(not (a & b) for k, a in enumerate(lanes) for b in lanes[k + 1:])
    out = wp.zeros(total, dtype=int, device="cpu")
    wp.launch(_lane_particles, dim=total, inputs=[0, 1], outputs=[out], device="cpu")
    assert out.numpy().tolist() == list(range(total))  # one part: particle t, as before the parts


def test_a_process_loading_kernels_builds_the_free_modules_first_then_waits_for_the_one_another_holds(tmp_path):
    # sim.runtime: a process that finds a module's lock file held (another process building it)
    # builds the other modules meanwhile, then waits for that lock and loads what the other
    # built (here this test holds the kernels module's lock until the others are ready)
    import fcntl
    import os
    import queue
    import subprocess
    import sys
    import threading
    import time

    cache = tmp_path / "kernels"
    cache.mkdir()
    env = dict(os.environ, WARP_CACHE_PATH=str(cache))
    code = ("import logging, sys; logging.basicConfig(level=logging.DEBUG, stream=sys.stdout); "
            f"from mosiv_ros.sim.simulator import load_kernels; load_kernels({DEVICE!r})")
    others = ("mosiv_ros.sim.params", "mosiv_ros.sim.effects", "mosiv_ros.sim.simulator")
    lines = []
    with open(cache / Path(lock_file(kernels.__name__)).name, "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        child = subprocess.Popen([sys.executable, "-u", "-c", code], env=env, stdout=subprocess.PIPE, text=True)
        printed: queue.Queue[str] = queue.Queue()
        reader = threading.Thread(target=lambda: [printed.put(line) for line in child.stdout], daemon=True)
        reader.start()
        try:
            while not all(any(f"kernels of {name} ready" in line for line in lines) for name in others):
                lines.append(printed.get(timeout=300))  # Empty: it waited before building them
            time.sleep(1.0)
            assert child.poll() is None  # still waiting for the lock
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    assert child.wait(timeout=600) == 0
    reader.join(timeout=60)
    while not printed.empty():
        lines.append(printed.get())
    out = "".join(lines)
    assert f"kernels of {kernels.__name__} ready" in out.split(f"kernels of {others[-1]} ready")[1]
    assert "waited" in out and "for another process building kernels into the cache" in out
    assert f"kernels ready on {DEVICE}" in out


def test_helper_processes_build_the_modules_the_cache_lacks_and_skip_those_another_process_holds(tmp_path,
                                                                                                    monkeypatch):
    # sim.runtime.build_aside and build_free, on an empty kernel cache of their own
    import fcntl
    import os

    from mosiv_ros.sim import runtime

    if (os.cpu_count() or 1) < 2:
        pytest.skip("a helper process needs a second core")
    cache = tmp_path / "kernels"
    cache.mkdir()
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(cache))  # where cached() and lock_file() look
    names = ["mosiv_ros.sim.params", "mosiv_ros.sim.simulator", "mosiv_ros.sim.effects"]
    assert not any(runtime.cached(runtime._module(name), DEVICE) for name in names)
    with open(lock_file(names[1]), "a") as lock:  # another process building the simulator's module
        fcntl.flock(lock, fcntl.LOCK_EX)
        assert runtime.start_helper(DEVICE, names[:2]).wait(timeout=600) == 0
    assert runtime.cached(runtime._module(names[0]), DEVICE)
    assert not any(runtime.cached(runtime._module(name), DEVICE) for name in names[1:])  # skipped, not waited for
    helpers = runtime.build_aside(DEVICE, names)  # two missing: one helper (two cores or more)
    assert len(helpers) == 1 and helpers[0].wait(timeout=600) == 0
    assert all(runtime.cached(runtime._module(name), DEVICE) for name in names)  # nothing else built them
    assert runtime.build_aside(DEVICE, names) == []  # none where the cache holds every module


def test_a_grid_that_g2p_clears_moves_as_one_cleared_whole():
    """A GPU's grids without gradients are cleared by G2P, each particle its stencil's nodes (``_Grid``).

    Two objects meeting, effects that write accelerations (drag) and stresses (a dashpot), two
    rows at their own time steps (so that one row's frame ends first and its particles skip
    substeps), and a second rollout on the same buffers: as a grid cleared whole every substep.
    A rollout clears the whole grid first, whatever a rollout before it left there (velocities
    that a diverged one left non-finite).
    """
    from mosiv_ros.sim.simulator import _Grid, _State

    runs = {}
    for clears in (False, True):
        sim = _two_balls(n_batch=2, effects=[Gravity(), LinearDrag(coefficient=2.0), KelvinVoigtDamping(viscosity=5.0)])
        sim.params.set("E", np.array([[3e4, 5e4], [3e5, 5e4]]))
        B, N = sim.n_batch, sim.n_particles
        sim._buffers = ([_State(B * N, sim.device, False) for _ in range(2)],
                        _Grid(B, sim.n_objects, sim.dims, B * N, sim._stress, sim.device, False, sim._accelerated,
                              clears=clears))
        assert sim._stress and sim._accelerated
        substeps = sim.own_time_steps()[0]
        assert substeps[0] < substeps[1]
        runs[clears] = (sim.rollout(3, own_steps=True), sim.rollout(2))
        if clears:  # what G2P leaves: nothing for the next substep to add to
            grid = sim._buffers[1]
            assert not grid.m.numpy().any() and not grid.p.numpy().any() and not grid.a.numpy().any()
            assert not grid.tau.numpy().any() and grid.v.numpy().any()
            grid.v.fill_(wp.vec3(np.nan, np.nan, np.nan))
            sim.rollout(1)
            assert np.isfinite(grid.v.numpy()).all()
    for cleared_whole, cleared_by_g2p in zip(runs[False], runs[True], strict=True):
        assert _equal(cleared_whole, cleared_by_g2p)


_ROOT = Path(__file__).resolve().parents[1]


def _benchmark(name: str):
    """The module of ``benchmarks/<name>.py``, loaded from its file (the folder is not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, _ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_kernel_profile_benchmark_times_every_kernel_of_a_frame(capsys, monkeypatch):
    """``benchmarks/sim_kernel_profile.py`` runs: it once broke unnoticed when ``_substep``'s arguments changed."""
    import json
    import sys

    monkeypatch.syspath_prepend(str(_ROOT / "benchmarks"))  # it imports sim_throughput's scene
    profile = _benchmark("sim_kernel_profile")
    monkeypatch.setattr(sys, "argv", ["sim_kernel_profile.py", "--device", DEVICE, "--particles", "500",
                                      "--repeats", "1"])
    assert profile.main() == 0
    result = json.loads(capsys.readouterr().out)
    for part in ("forward_s", "adjoint_s"):
        times = result[part]
        assert "g2p" in times and any(name.endswith("p2g") for name in times), times
        assert any(name.startswith("grid_update") for name in times), times
        assert all(t > 0 for t in times.values())
    assert result["frame_s"]["forward"] > 0 and result["frame_s"]["backward"] > 0


def test_the_loss_benchmark_sums_the_devices_idle_time_by_the_work_around_it():
    """``loss_throughput.device_idle`` on a trace: host events and work inside other work leave no gap."""
    benchmark = _benchmark("loss_throughput")
    events = [{"cat": "kernel", "name": "p2g_0123abcd_cuda_kernel_forward", "ts": 100.0, "dur": 10.0},
              {"cat": "gpu_memset", "name": "Memset (Device)", "ts": 101.0, "dur": 2.0},  # inside P2G
              {"cat": "cpu_op", "name": "aten::copy_", "ts": 111.0, "dur": 30.0},  # the host's
              {"cat": "kernel", "name": "g2p_89abcdef_cuda_kernel_forward", "ts": 112.0, "dur": 5.0},
              {"cat": "gpu_memcpy", "name": "Memcpy DtoH", "ts": 120.0, "dur": 3.0},
              {"cat": "kernel", "name": "p2g_0123abcd_cuda_kernel_forward", "ts": 123.5, "dur": 1.0},
              {"cat": "kernel", "name": "g2p_89abcdef_cuda_kernel_forward", "ts": 126.5, "dur": 1.0}]
    idle = benchmark.device_idle(events)
    assert idle["span_us"] == 27.5 and idle["idle_us"] == 7.5 and idle["busy_us"] == 20.0
    gaps = {(g["after"], g["before"]): (g["count"], g["idle_us"]) for g in idle["gaps"]}
    assert gaps == {("p2g_forward", "Memset (Device)"): (1, 0.0), ("p2g_forward", "g2p_forward"): (2, 4.0),
                    ("g2p_forward", "Memcpy DtoH"): (1, 3.0), ("Memcpy DtoH", "p2g_forward"): (1, 0.5)}
    assert [g["idle_us"] for g in idle["gaps"]] == [4.0, 3.0, 0.5, 0.0]
    assert benchmark.device_idle([]) == {"span_us": 0.0, "busy_us": 0.0, "idle_us": 0.0, "gaps": []}


@pytest.mark.skipif(DEVICE == "cpu", reason="torch's profiler sees Warp's kernels on a CUDA device: "
                                            "run with MOSIV_TEST_DEVICE=cuda:0")
def test_the_loss_benchmark_gives_each_kernels_device_time_a_substep(monkeypatch, tmp_path):
    """``benchmarks/loss_throughput.py --kernels``: a window's kernels forward and backward, a search's."""
    import json
    import sys

    benchmark = _benchmark("loss_throughput")
    out = tmp_path / "kernels.json"
    monkeypatch.setattr(sys, "argv", ["loss_throughput.py", str(_ROOT / "bags" / "pressed_cube"), "--device", DEVICE,
                                      "--params-file", str(_ROOT / "config" / "mosiv.yaml"), "--rows", "2",
                                      "--repeats", "1", "--kernels", "--out", str(out)])
    assert benchmark.main() == 0
    kernels = json.loads(out.read_text())["results"][0]["kernels"]
    window, search = kernels["window"], kernels["search"]
    assert window["substeps"] > 0 and search["substeps"] > 0
    names = set(window["per_substep_us"])
    assert {"g2p_forward", "g2p_adjoint_forward"} <= names, names
    assert any("p2g" in name and name.endswith("_backward") for name in names), names
    assert not any(name.endswith("_backward") for name in search["per_substep_us"])  # the search has no gradient
    # a substep's adjoint once (a backward that recomputes its frames launches G2P again)
    assert 0 < window["launches"]["g2p_adjoint_forward"] <= window["substeps"]
    assert 0 < window["idle"]["busy_us"] <= window["idle"]["span_us"] and window["idle"]["gaps"]


@pytest.mark.skipif(DEVICE == "cpu", reason="torch's profiler sees Warp's kernels on a CUDA device: "
                                            "run with MOSIV_TEST_DEVICE=cuda:0")
def test_the_throughput_benchmark_gives_each_kernels_device_time_a_substep_of_the_search(monkeypatch):
    """``benchmarks/sim_throughput.py --batch B --kernels``: the search's case, kernel by kernel."""
    monkeypatch.syspath_prepend(str(_ROOT / "benchmarks"))  # it imports loss_throughput's profiler
    benchmark = _benchmark("sim_throughput")
    result = benchmark.run_one(500, 2, 2, DEVICE, 0.0, batch=4, kernels=True)
    kernels = result["kernels"]
    assert kernels["substeps"] == 2 * result["substeps_per_frame"]  # the two forward frames, once
    names = set(kernels["per_substep_us"])
    assert "g2p_forward" in names and any("p2g" in name for name in names), names
    assert not any(name.endswith("_backward") for name in names)  # forward only, as the search runs
    assert 0 < kernels["idle"]["busy_us"] <= kernels["idle"]["span_us"]
