"""Simulator gradients of a Chamfer loss against central finite differences (CPU, float32).

Each case fits a ball's rollout to the rollout of other parameters (so the loss is not at a
minimum) and compares dL/dtheta from ``Simulator.backward`` with the least-squares slope of the
loss through theta +- h and theta +- 2h, the substep count held fixed (the CFL bound would
otherwise change the discretisation), and h = 0.1 % of the value: ground contact (particles
projected back onto the floor, grid nodes on it held) makes the loss kinked on the scale of a 1 %
step, which larger steps average over, and a single central difference at h scatters by up to
12 % around the slope. Measured agreement is 0.2-4 % for every parameter family; the tolerance
is 5 %.
"""

from __future__ import annotations

import numpy as np
import pytest
from sim_scenes import DEVICE, falling_ball, scene

from mosiv_ros.identify.losses import chamfer
from mosiv_ros.sim import BodyForce, Ground, KelvinVoigtDamping, LinearDrag, ObjectModel, QuadraticDrag
from mosiv_ros.sim.effects import FIELD_FEATURES, ForceField
from mosiv_ros.sim.sampling import cylinder, sphere

FRAMES = (3, 6)
REPEATS, STEP_SCALE = (1, 1.0) if DEVICE == "cpu" else (4, 3.0)
"""Rollouts per finite-difference point, and the factor on each test's step: a CPU repeats a
rollout to the bit; a GPU adds its float atomics in no fixed order, so there the mean of a few
rollouts over a three times larger step keeps that noise below the differences (at the CPU's
step nu's slope came out 7 % off on an H200, 4 % on the CPU; at three times the step 0.2 % on
the CPU; at ten times the loss's kinks show, 16 % off on both)."""


def loss(sim, target, substeps, grad=False, frames=FRAMES):
    traj = sim.rollout(frames[-1], grad=grad, substeps=substeps)
    total, dL = 0.0, np.zeros_like(traj, dtype=np.float64)
    for f in frames:
        value, g = chamfer(traj[f, 0].astype(np.float64), target[f])
        total += value
        dL[f, 0] = g
    return total, dL


def check(sim, target, name, index, step, frames=FRAMES):
    """Assert dL/d(name[index]) against finite differences; returns all gradients."""
    substeps = sim.time_step()[0] + 2
    _, dL = loss(sim, target, substeps, grad=True, frames=frames)
    grads = sim.backward(dL)
    analytic = grads.params[name][index]
    base = sim.params.get(name)
    shifts = np.array([1.0, -1.0, 2.0, -2.0]) * step * STEP_SCALE
    values = []
    for shift in shifts:
        shifted = base.copy()
        shifted[index] += shift
        sim.params.set(name, shifted)
        values.append(np.mean([loss(sim, target, substeps, frames=frames)[0]
                               for _ in range(REPEATS)]))
    sim.params.set(name, base)
    # least-squares slope through L(theta +- h) and L(theta +- 2h)
    numeric = float(shifts @ np.array(values) / (shifts @ shifts))
    print(f"{name}: analytic {analytic:.4g}, finite differences {numeric:.4g}")
    assert numeric != 0.0
    assert analytic == pytest.approx(numeric, rel=0.05)
    return grads


def target_of(family, params, effects=(), **values):
    sim = falling_ball(family, params, effects)
    sim.params.update(values)
    return sim.rollout(FRAMES[-1])[:, 0].astype(np.float64)


@pytest.mark.parametrize(("name", "index", "rel_step"), [
    ("E", (0, 0), 0.001), ("nu", (0, 0), 0.001), ("ground.friction", (0,), 0.001),
    ("gravity.g", (0, 2), 0.001), ("density", (0, 0), 0.001),
])
def test_elastic_and_ground_gradients_match_finite_differences(name, index, rel_step):
    target = target_of("elastic", {"E": 6e4, "nu": 0.2}, **{"gravity.g": (0.5, 0.0, -9.0)})
    sim = falling_ball("elastic", {"E": 3e4, "nu": 0.3})
    step = rel_step * abs(sim.params.get(name)[index])
    check(sim, target, name, index, step)


def test_a_second_uniform_acceleration_gradient_matches_finite_differences():
    # gravity and a wind are both uniform: the grid passes read their sum (Simulator._replicate)
    target = target_of("elastic", {"E": 3e4}, (BodyForce(a=(1.0, 0.0, -0.5)),))
    sim = falling_ball("elastic", {"E": 3e4}, (BodyForce(a=(0.3, 0.0, 0.0)),))
    grads = check(sim, target, "wind.a", (0, 0), 0.01)
    # the same sum's gradient (equal on the CPU; the GPU folds the replicas in no fixed order)
    assert np.allclose(grads.params["wind.a"], grads.params["gravity.g"], rtol=1e-5, atol=1e-12)


@pytest.mark.parametrize(("family", "fit", "true", "name"), [
    ("plastic", {"E": 3e4, "yield_stress": 800.0}, {"E": 3e4, "yield_stress": 1500.0},
     "yield_stress"),
    ("plastic", {"E": 3e4, "yield_stress": 800.0}, {"E": 3e4, "yield_stress": 1500.0}, "E"),
    ("sand", {"E": 3e4, "friction_angle": 0.5}, {"E": 3e4, "friction_angle": 0.7},
     "friction_angle"),
    ("fluid", {"bulk_modulus": 3e4, "viscosity": 1.0}, {"bulk_modulus": 5e4, "viscosity": 3.0},
     "bulk_modulus"),
    ("fluid", {"bulk_modulus": 3e4, "viscosity": 1.0}, {"bulk_modulus": 5e4, "viscosity": 3.0},
     "viscosity"),
])
def test_material_family_gradients_match_finite_differences(family, fit, true, name):
    target = target_of(family, true)
    sim = falling_ball(family, fit)
    step = 0.001 * abs(sim.params.get(name)[0, 0])
    check(sim, target, name, (0, 0), step)


def sand_pile(friction_angle):
    """A sand column (640 particles) that collapses under gravity into a pile on the ground."""
    dx, floor = 0.02, 0.08
    column = cylinder((0.2, 0.2, floor + 0.04), 0.05, 0.04, dx / 2)
    return scene([column], [ObjectModel("sand", "sand", {"E": 1e5, "density": 1600.0,
                                                         "friction_angle": friction_angle})],
                 dx=dx, lo=(0, 0, 0), hi=(0.4, 0.4, 0.26), frame_dt=1 / 30,
                 ground=Ground(height=floor, friction=0.5))


def test_settled_sand_pile_gradients_are_finite_and_match_finite_differences():
    # The pile has settled by frame 8 (mean speed 2 mm/s after a peak of 0.27 m/s) and creeps
    # on. In frame 17 (16-18 at 60-63 substeps a frame) the four particles on its diagonals at
    # its foot cross half-cell points along x and y at once: the quadratic B-spline puts about
    # 1e-25 of their mass on the nodes across, whose square is 0 in float32, and the adjoint of
    # p / m (kernels.divide) made every gradient of the rollout NaN.
    frames = (10, 15, 20)
    target = sand_pile(0.5).rollout(frames[-1])[:, 0].astype(np.float64)
    sim = sand_pile(0.35)
    grads = check(sim, target, "friction_angle", (0, 0), 0.00035, frames)
    for name, values in grads.params.items():
        assert np.all(np.isfinite(values)), name
    assert np.all(np.isfinite(grads.v0))
    assert np.all(np.isfinite(grads.volume))


def test_gradients_stay_finite_at_nodes_that_only_a_spline_tip_reaches():
    # One particle 2^-20 cell short of a half-cell point along x and y (exact in float32 with
    # dx = 0.25): the nodes across get 2^-82 of its weight, 3e-26 kg, whose square is 0 in
    # float32.
    x = np.array([[1.375 - 2.0**-22, 1.375 - 2.0**-22, 1.5]])
    sim = scene([(x, 0.125**3)], [ObjectModel("ball", "elastic", {"E": 1e4})], dx=0.25,
                lo=(0, 0, 0), hi=(3, 3, 3), velocities=[(0.1, 0.2, 0.0)])
    traj = sim.rollout(1, grad=True)
    grads = sim.backward(np.ones_like(traj, dtype=np.float64))
    for name, values in grads.params.items():
        assert np.all(np.isfinite(values)), name
    assert np.all(np.isfinite(grads.v0))
    assert np.all(np.isfinite(grads.volume))


@pytest.mark.parametrize("name", ["drag.coefficient", "damping.viscosity",
                                  "linear_drag.coefficient"])
def test_effect_gradients_match_finite_differences(name):
    def effects():
        return (QuadraticDrag(coefficient=1.0), KelvinVoigtDamping(viscosity=5.0),
                LinearDrag(coefficient=0.5))

    target = target_of("elastic", {"E": 3e4}, effects(), **{
        "drag.coefficient": 2.0, "damping.viscosity": 10.0, "linear_drag.coefficient": 1.0})
    sim = falling_ball("elastic", {"E": 3e4}, effects())
    check(sim, target, name, (0, 0), 0.001 * sim.params.get(name)[0, 0])


@pytest.mark.parametrize(("term", "axis"), [("x", 0), ("vz", 2), ("|v| vx", 0)])
def test_force_field_gradients_match_finite_differences(term, axis):
    index = 3 * FIELD_FEATURES.index(term) + axis

    def effects(value):
        w = np.zeros(3 * len(FIELD_FEATURES))
        w[index] = value
        return (ForceField(w=tuple(w), origin=(0.2, 0.2, 0.14)),)

    target = target_of("elastic", {"E": 3e4}, effects(-4.0))
    sim = falling_ball("elastic", {"E": 3e4}, effects(-1.0))
    check(sim, target, "force_field.w", (0, index), 0.01)


@pytest.mark.parametrize(("objects", "step"), [(2, 0.01), (3, 0.001)])
def test_object_friction_gradient_matches_finite_differences(objects, step):
    """Two balls meeting, or three at once: the grid update's contact sums are unrolled per object count.

    The slope through mu +- h, +- 2h (``check``'s) against the analytic gradient, measured on the
    CPU: two balls 1.8 / 1.9 / 3.3 / 6.3 % off at h = 0.03 / 0.01 / 0.003 / 0.001 (stick and slip
    switch at nodes on a small scale), three 7.9 / 6.9 / 3.3 / 0.8 % (their loss curves on a
    larger one). Each takes the step its loss is smooth at, times ``STEP_SCALE``.
    """
    dx = 0.02
    solids = [sphere((0.2, 0.2, 0.2), 0.05, dx / 2), sphere((0.3, 0.22, 0.2), 0.05, dx / 2),
              sphere((0.25, 0.31, 0.2), 0.05, dx / 2)][:objects]
    velocities = [(1.5, 0.0, 0.0), (-0.5, 0.0, 0.0), (0.0, -1.0, 0.0)][:objects]

    def make(mu_a):
        return scene(solids, [ObjectModel("a", "elastic", {"E": 3e4, "friction": mu_a}),
                              ObjectModel("b", "elastic", {"E": 3e4, "friction": 0.5}),
                              ObjectModel("c", "elastic", {"E": 3e4, "friction": 0.3})][:objects],
                     dx=dx, lo=(0, 0, 0), hi=(0.5, 0.4 if objects == 2 else 0.5, 0.4), effects=[],
                     velocities=velocities)

    target = make(0.1).rollout(FRAMES[-1])
    fit = make(0.4)
    both = target[:, 0].astype(np.float64)

    def pair_loss(grad, substeps):
        traj = fit.rollout(FRAMES[-1], grad=grad, substeps=substeps)
        total, dL = 0.0, np.zeros_like(traj, dtype=np.float64)
        for f in FRAMES:  # per object, as the identifier will do
            for k in range(objects):
                mask = fit.object_index() == k
                value, g = chamfer(traj[f, 0, mask].astype(np.float64), both[f, mask])
                total += value
                dL[f, 0, mask] = g
        return total, dL

    substeps = fit.time_step()[0]
    _, dL = pair_loss(True, substeps)
    analytic = fit.backward(dL).params["friction"][0, 0]
    shifts = np.array([1.0, -1.0, 2.0, -2.0]) * step * STEP_SCALE
    values = []
    for shift in shifts:
        fit.params.set("friction", {"a": 0.4 + shift})
        values.append(np.mean([pair_loss(False, substeps)[0] for _ in range(REPEATS)]))
    numeric = float(shifts @ np.array(values) / (shifts @ shifts))
    assert numeric != 0.0
    assert analytic == pytest.approx(numeric, rel=0.05)


def test_initial_velocity_and_volume_gradients_match_finite_differences():
    target = target_of("elastic", {"E": 6e4})
    sim = falling_ball("elastic", {"E": 3e4})
    substeps = sim.time_step()[0] + 2
    _, dL = loss(sim, target, substeps, grad=True)
    grads = sim.backward(dL)
    v0 = sim.initial_velocity()[0].astype(np.float64)
    volume = sim.volumes()[0].astype(np.float64)

    # Directional derivatives: a uniform change of the x velocity; more volume (mass) in the
    # upper half of the ball (a uniform volume scaling would change nothing: mass and stress
    # scale together).
    upper = volume * (sim.initial_positions()[:, 2] > sim.initial_positions()[:, 2].mean())

    def at(v_shift=0.0, volume_shift=0.0):
        sim.set_initial_velocity(v0 + [v_shift, 0.0, 0.0])
        sim.set_volume(volume + volume_shift * upper)
        return loss(sim, target, substeps)[0]

    numeric_v = (at(v_shift=0.001) - at(v_shift=-0.001)) / 0.002
    assert grads.v0[0, :, 0].sum() == pytest.approx(numeric_v, rel=0.05)
    numeric_volume = (at(volume_shift=0.005) - at(volume_shift=-0.005)) / 0.01
    assert numeric_volume != 0.0
    assert grads.volume[0] @ upper == pytest.approx(numeric_volume, rel=0.05)


def test_gradients_with_a_moving_collider_match_finite_differences():
    # A sphere sweeps through the falling ball, one frame's poses differing from the next's: the
    # backward pass recomputes each frame with that frame's poses (on the CPU while the adjoint
    # of the frame after it runs, on buffers of its own).
    from mosiv_ros.sim import Collider, Gravity

    def pushed(params):
        finger = Collider("sphere", (0.03,), np.array([0.0, 0.12]),
                          np.array([[0.08, 0.2, 0.12], [0.32, 0.2, 0.12]]), friction=0.5)
        return scene([sphere((0.2, 0.2, 0.14), 0.05, 0.01)], [ObjectModel("ball", "elastic", params)],
                     dx=0.02, lo=(0, 0, 0), hi=(0.4, 0.4, 0.3), colliders=[finger],
                     ground=Ground(height=0.08, friction=0.4), effects=[Gravity()])

    target = pushed({"E": 6e4, "nu": 0.2}).rollout(FRAMES[-1])[:, 0].astype(np.float64)
    sim = pushed({"E": 3e4, "nu": 0.3})
    check(sim, target, "E", (0, 0), 0.001 * abs(sim.params.get("E")[0, 0]))


def generated_twin(forward, written, names: tuple):
    """(Warp's kernel of ``forward``'s function with its generated adjoint, ``forward``'s argument names).

    The forward kernel has no generated adjoint of its own; ``written`` must take its arguments,
    then the adjoints of those that ``names`` lists.
    """
    import warp as wp

    generated = wp.Kernel(forward.func, key=f"{forward.key}_with_generated_adjoint", module=wp.get_module(__name__),
                          options={"enable_backward": True})
    labels = [arg.label for arg in forward.adj.args]
    assert [arg.label for arg in written.adj.args] == [*labels, *(f"adj_{name}" for name in names)]
    return generated, labels


def written_adjoint_matches(tape, written, dim: int, args: list, inputs: dict, outputs: list, names: tuple,
                            rng: np.random.Generator, rtol: float, atol: float, unused: tuple = ()) -> None:
    """Assert a written adjoint kernel adds what Warp's generated adjoint on ``tape`` adds.

    The outputs' adjoints are seeded at random and ``tape`` run backward; then ``written`` runs
    over ``dim`` threads from zeroed input adjoints, with the forward's ``args``, the
    ``outputs``, the adjoints of the inputs that ``names`` lists, then the outputs' adjoints.
    Every input's adjoint must be within ``rtol``, and ``atol`` times its largest magnitude, of
    Warp's, and nonzero unless ``unused`` names it (then both are zero).
    """
    import warp as wp

    for out in outputs:
        out.grad.assign(rng.normal(size=out.grad.numpy().shape).astype(np.float32))
    tape.backward()
    warps = {name: array.grad.numpy().copy() for name, array in inputs.items()}
    for array in inputs.values():
        array.grad.zero_()
    wp.launch(written, dim, inputs=[*args, *outputs, *(inputs[name].grad for name in names[:len(names) - len(outputs)]),
                                    *(out.grad for out in outputs)], device=DEVICE)
    for name, array in inputs.items():
        assert (np.abs(warps[name]).max() > 0) != (name in unused), name
        assert np.allclose(array.grad.numpy(), warps[name], rtol=rtol, atol=atol * np.abs(warps[name]).max()), name


def test_g2p_written_adjoint_adds_what_warps_generated_adjoint_adds():
    """``kernels.g2p_adjoint`` against Warp's generated adjoint of ``kernels.g2p``'s function on random inputs.

    Two rows (the second past its own substeps, so it only copies its state), two objects'
    fields, a tilted ground plane that about half the particles end up under, random velocity,
    affine and output adjoints: every input's adjoint within float32 rounding of Warp's.
    """
    import warp as wp

    from mosiv_ros.sim import kernels
    from mosiv_ros.sim.params import REPLICAS
    from mosiv_ros.sim.simulator import _G2P_ADJOINTS

    # kernels.g2p has no generated adjoint: the same function, built here with one
    generated, g2p_args = generated_twin(kernels.g2p, kernels.g2p_adjoint, _G2P_ADJOINTS)
    rng = np.random.default_rng(3)
    B, N, K, dims, dx = 2, 400, 2, (8, 7, 9), 0.1
    G = int(np.prod(dims))

    def array(values, dtype, grad=True):
        return wp.array(np.asarray(values, np.float32), dtype=dtype, device=DEVICE, requires_grad=grad)

    x = rng.uniform([0.12, 0.12, 0.12], [0.65, 0.55, 0.75], size=(B * N, 3))
    inputs = {"src_x": array(x, wp.vec3), "src_v": array(rng.normal(size=(B * N, 3)), wp.vec3),
              "src_C": array(rng.normal(size=(B * N, 3, 3)), wp.mat33),
              "grid_v": array(rng.normal(size=(B * K * G, 3)), wp.vec3),
              "ground_height": array(np.repeat([0.45, 0.3], REPLICAS), float),
              "ground_normal": array(np.repeat([0.1, 0.2, 1.0, -0.1, 0.05, 0.9], REPLICAS), float)}
    outputs = [array(np.zeros((B * N, 3)), wp.vec3), array(np.zeros((B * N, 3)), wp.vec3),
               array(np.zeros((B * N, 3, 3)), wp.mat33)]
    # the grid's other arrays, which only a grid that G2P clears (none on a tape) has it write
    grid = {"grid_m": wp.zeros(B * K * G, dtype=float, device=DEVICE),
            "grid_p": wp.zeros(B * K * G, dtype=wp.vec3, device=DEVICE),
            "grid_a": wp.zeros(0, dtype=wp.vec3, device=DEVICE),
            "grid_tau": wp.zeros(0, dtype=wp.mat33, device=DEVICE), "grid_clears": 0}
    given = {**inputs, **grid, "obj": wp.array(rng.integers(0, K, N).astype(np.int32), dtype=int, device=DEVICE),
             "has_ground": 1, "n_particles": N, "block_warps": 8, "n_objects": K, "n_nodes": G,
             "dims": wp.vec3i(*dims), "lo": wp.vec3(0.0), "dx": dx, "dt": 0.01,
             "own_dt": array([0.03, 0.02], float, grad=False),
             "own_substeps": wp.array([5, 3], dtype=int, device=DEVICE), "substep": 4}
    args = [given[name] for name in g2p_args[:-3]]
    tape = wp.Tape()
    with tape:
        wp.launch(generated, B * N, inputs=args, outputs=outputs, device=DEVICE)
    below = (outputs[0].numpy()[:N] @ np.array([0.1, 0.2, 1.0]) / np.linalg.norm([0.1, 0.2, 1.0])
             < 0.45 + 1e-6)
    assert 0.2 < below.mean() < 0.8  # the ground's projection and its adjoint are exercised
    written_adjoint_matches(tape, kernels.g2p_adjoint, B * N, args, inputs, outputs, _G2P_ADJOINTS, rng, 1e-5, 1e-6)


@pytest.mark.parametrize("only", [-1, 0, 1, 2, 3], ids=["any", "elastic", "plastic", "sand", "fluid"])
def test_p2g_written_adjoint_adds_what_warps_generated_adjoint_adds(only):
    """P2G's written adjoint against Warp's generated adjoint of ``kernels.p2g``'s function on random inputs.

    Two rows (the second past its own substeps, so it only copies b), four objects, trial
    states that take every branch of the return mappings (a plastic particle inside and outside
    its yield surface; sand in tension, inside its cone and outside it), an effect's stress,
    random velocities, affine fields and output adjoints: every input's adjoint within float32
    rounding of Warp's. The objects are one of each family for the kernel of any family, and
    all of one family for that family's (``kernels.p2g_adjoint_kernel``).
    """
    import warp as wp

    from mosiv_ros.sim import kernels
    from mosiv_ros.sim.materials import ALL, FAMILY_PARAMS, MATERIAL_PARAM_NAMES
    from mosiv_ros.sim.params import REPLICAS
    from mosiv_ros.sim.simulator import _P2G_ADJOINTS

    # kernels.p2g has no generated adjoint: the same function, built here with one
    written = kernels.p2g_adjoint_kernel(only)
    generated, p2g_args = generated_twin(kernels.p2g, written, _P2G_ADJOINTS)
    rng = np.random.default_rng(11)
    B, N, K, dims, dx = 2, 480, 4, (8, 7, 9), 0.1
    G = int(np.prod(dims))
    h = np.float32(2e-3)

    def array(values, dtype, grad=True):
        return wp.array(np.asarray(values, np.float32), dtype=dtype, device=DEVICE, requires_grad=grad)

    def per_object(values):  # a parameter's replicas, the same values in both rows
        return array(np.repeat(np.tile(values, B), REPLICAS), float)

    obj = np.arange(N) % K
    families = np.arange(K) if only < 0 else np.full(K, only)  # elastic, plastic, sand, fluid by code
    stretch = rng.uniform(0.85, 1.15, size=(B * N, 1, 1)) * np.eye(3)
    L = stretch + rng.normal(scale=0.12, size=(B * N, 3, 3))
    b = L @ np.transpose(L, (0, 2, 1))
    C = rng.normal(scale=3.0, size=(B * N, 3, 3))
    E, nu = np.array([2e4, 3e4, 2.5e4, 1e4]), np.array([0.3, 0.25, 0.2, 0.3])
    yield_stress, friction_angle = np.array([1e4, 5e3, 1e4, 1e4]), np.array([0.5, 0.5, 1.0, 0.5])
    inputs = {"src_x": array(rng.uniform(0.15, 0.6, size=(B * N, 3)), wp.vec3),
              "src_v": array(rng.normal(size=(B * N, 3)), wp.vec3), "src_C": array(C, wp.mat33),
              "src_b": array(b, wp.mat33), "volume": array(rng.uniform(0.5e-4, 2e-4, size=B * N), float),
              "grid_tau": array(rng.normal(scale=50.0, size=(B * N, 3, 3)), wp.mat33),
              "E": per_object(E), "nu": per_object(nu), "yield_stress": per_object(yield_stress),
              "friction_angle": per_object(friction_angle), "bulk_modulus": per_object([1e4, 1e4, 1e4, 2e4]),
              "viscosity": per_object([1.0, 1.0, 1.0, 0.5]), "density": per_object([1e3, 1.2e3, 1.5e3, 1e3])}
    outputs = [array(np.zeros((B * N, 3, 3)), wp.mat33), array(np.zeros(B * K * G), float),
               array(np.zeros((B * K * G, 3)), wp.vec3)]
    given = {**inputs, "obj": wp.array(obj.astype(np.int32), dtype=int, device=DEVICE),
             "family": wp.array(families.astype(np.int32), dtype=int, device=DEVICE),
             "n_particles": N, "plane_threads": B * N, "part": 0, "parts": 1, "plane_warps": 8, "n_objects": K,
             "n_nodes": G, "dims": wp.vec3i(*dims), "lo": wp.vec3(0.0), "dx": dx,
             "own_dt": array([h, h], float, grad=False),
             "own_substeps": wp.array([5, 3], dtype=int, device=DEVICE), "substep": 4}
    args = [given[name] for name in p2g_args[:-3]]
    tape = wp.Tape()
    with tape:
        wp.launch(generated, B * N, inputs=args, outputs=outputs, device=DEVICE)
    # the branches the first row's trial states take (materials.return_mapping)
    f = np.eye(3) + C[:N] * h
    trial = f @ b[:N] @ np.transpose(f, (0, 2, 1))
    J = np.sqrt(np.linalg.det(trial))
    mu = E[obj] / (2 * (1 + nu[obj]))
    kappa = E[obj] * nu[obj] / ((1 + nu[obj]) * (1 - 2 * nu[obj])) + 2 / 3 * mu
    dev = trial - np.trace(trial, axis1=1, axis2=2)[:, None, None] / 3 * np.eye(3)
    s = mu * J ** (-2 / 3) * np.sqrt((dev ** 2).sum(axis=(1, 2)))
    sin_phi = np.sin(friction_angle[obj])
    p = 0.5 * kappa * (J * J - 1)
    plastic, sand = families[obj] == 1, families[obj] == 2
    yielded = s > np.sqrt(2 / 3) * yield_stress[obj]
    outside = s > -3 * np.sqrt(2 / 3) * 2 * sin_phi / (3 - sin_phi) * p
    shares = [yielded[plastic].mean()] if plastic.any() else []
    if sand.any():
        shares += [(p >= 0)[sand].mean(), (outside & (p < 0))[sand].mean(), (~outside & (p < 0))[sand].mean()]
    for share in shares:
        assert 0.1 < share < 0.9
    unused = () if only < 0 else tuple(set(MATERIAL_PARAM_NAMES) - set(FAMILY_PARAMS[ALL[only]]))
    written_adjoint_matches(tape, written, B * N, args, inputs, outputs, _P2G_ADJOINTS, rng, 1e-4, 1e-5, unused)


@pytest.mark.parametrize("colliders, objects", [(0, 1), (0, 2), (2, 2), (0, 3)])
def test_grid_update_written_adjoint_adds_what_warps_generated_adjoint_adds(colliders, objects):
    """The grid update's written adjoint against Warp's generated adjoint of the update, on random inputs.

    Two rows of ``objects`` fields whose masses overlap in a band of the grid (the object
    contact), node accelerations, a tilted ground under about a third of the nodes, a sphere
    and a rotated box among the nodes where the kernel has the colliders' code, walls on every
    face, random velocity adjoints: every input's adjoint within float32 rounding of Warp's,
    and the velocities those of the function Warp differentiates.
    """
    import warp as wp

    from mosiv_ros.sim import kernels
    from mosiv_ros.sim.params import REPLICAS
    from mosiv_ros.sim.simulator import _GRID_UPDATE_ADJOINTS

    forward, written = kernels.grid_update_kernels(colliders, objects)
    generated, labels = generated_twin(forward, written, _GRID_UPDATE_ADJOINTS)
    rng = np.random.default_rng(5)
    B, dims, dx = 2, (8, 7, 9), 0.1
    G = int(np.prod(dims))
    ii, jj, ll = (axis.ravel() for axis in np.meshgrid(*map(np.arange, dims), indexing="ij"))
    x_node = np.stack([ii, jj, ll], axis=1) * dx

    def array(values, dtype, grad=True):
        return wp.array(np.asarray(values, np.float32), dtype=dtype, device=DEVICE, requires_grad=grad)

    # field k holds mass in a slab along x that overlaps the next field's, and none elsewhere
    masses = np.zeros((B, objects, G))
    for k in range(objects):
        inside = (ii >= 2 * k + 1) & (ii <= 2 * k + 4) & (ll >= 1) & (ll <= 6)
        masses[:, k, inside] = rng.uniform(0.2, 2.0, size=(B, inside.sum()))
    masses[masses > 0] *= rng.random(np.count_nonzero(masses)) > 0.1  # some empty nodes among them
    momenta = rng.normal(size=(B * objects * G, 3)) * masses.reshape(-1, 1)
    size = (colliders or 1) * 2  # the poses of two substeps
    inputs = {"grid_m": array(masses.ravel(), float), "grid_p": array(momenta, wp.vec3),
              "grid_a": array(rng.normal(size=(B * objects * G, 3)), wp.vec3),
              "uniform": array(np.repeat([0.1, -0.2, -9.8, 0.3, 0.0, -9.6], REPLICAS), float),
              "friction": array(np.repeat(rng.uniform(0.1, 0.8, B * objects), REPLICAS), float),
              "ground_normal": array(np.repeat([0.1, 0.2, 1.0, -0.1, 0.05, 0.9], REPLICAS), float),
              "ground_friction": array(np.repeat([0.4, 0.7], REPLICAS), float)}
    ranks = wp.array(np.arange(objects, dtype=np.int32)[::-1].copy(), dtype=int, device=DEVICE)  # the last leads
    given = {**inputs, "normal_rank": ranks, "ranked_object": ranks,
             "ground_height": array(np.repeat([0.3, 0.25], REPLICAS), float), "has_ground": 1,
             "collider_shape": wp.array([0, 1], dtype=int, device=DEVICE),
             "collider_size": array([[0.2, 0.0, 0.0], [0.15, 0.1, 0.2]], wp.vec3, grad=False),
             "collider_friction": array([0.3, 0.6], float, grad=False),
             "collider_pos": array(np.tile([[0.45, 0.3, 0.5], [0.25, 0.35, 0.35]], (size // 2, 1)), wp.vec3,
                                   grad=False),
             "collider_rot": array(np.tile([[0.0, 0.0, 0.0, 1.0], [0.0, 0.2588, 0.0, 0.9659]], (size // 2, 1)),
                                   wp.quat, grad=False),
             "collider_vel": array(rng.normal(size=(size, 3)), wp.vec3, grad=False),
             "collider_omega": array(rng.normal(size=(size, 3)), wp.vec3, grad=False),
             "substep": 1, "collider_count": 2, "n_nodes": G, "dims": wp.vec3i(*dims), "box_lo": wp.vec3i(0, 0, 0),
             "box_dims": wp.vec3i(*dims), "lo": wp.vec3(0.0), "dx": dx,
             "own_dt": array([0.01, 0.02], float, grad=False),
             "grid_v": array(np.zeros((B * objects * G, 3)), wp.vec3)}
    args = [given[name] for name in labels]
    tape = wp.Tape()
    with tape:
        wp.launch(generated, B * objects * G, inputs=args, device=DEVICE)
    velocities = given["grid_v"].numpy().copy()
    given["grid_v"].zero_()
    wp.launch(forward, B * objects * G, inputs=args, device=DEVICE)
    assert np.array_equal(given["grid_v"].numpy(), velocities)
    unused = ("friction",) if objects == 1 else ()  # the objects' friction acts only in their contact
    written_adjoint_matches(tape, written, B * objects * G, args[:-1], inputs, [given["grid_v"]],  # grid_v: the last
                            _GRID_UPDATE_ADJOINTS, rng, 1e-5, 1e-6, unused)
    # each branch was taken: the ground under a third of the nodes, the walls, contact, the colliders
    held = np.abs(velocities).max(axis=1).reshape(B, objects, G) > 0
    on_ground = x_node @ np.array([0.1, 0.2, 1.0]) / np.linalg.norm([0.1, 0.2, 1.0]) < 0.3
    assert 0.2 < on_ground.mean() < 0.5 and held[:, :, on_ground].any()
    shared = (masses > 0).sum(axis=1) > 1
    assert (objects == 1) == (not shared.any())


def test_p2g_scatter_adjoint_adds_what_warps_generated_adjoint_of_its_atomics_adds():
    """``kernels.scatter_plane``'s written adjoint against Warp's of the same scatter as plain atomics.

    Random stencil weights, masses, momenta and corners, two threads on each plane of a stencil
    (a run of lanes that adds once on a GPU) in two objects' fields, random node adjoints: the
    grid's sums and every input's adjoint within float32 rounding of the ones Warp generates for
    the nine atomic adds written out, and the grid untouched by the backward pass.
    """
    import warp as wp

    from mosiv_ros.sim import kernels
    from mosiv_ros.sim.warp_reduce import run_start

    @wp.func
    def plain(grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3), a: int, w_a: float,
              wy: wp.vec3, wz: wp.vec3, mass: float, at_origin: wp.vec3, per_x: wp.vec3, per_y: wp.vec3,
              per_z: wp.vec3, offset: int, base: wp.vec3i, dims: wp.vec3i):
        for c in range(3):
            for e in range(3):
                weight = w_a * wy[c] * wz[e]
                node = offset + kernels.node_index(base[0] + a, base[1] + c, base[2] + e, dims)
                p_node = at_origin + per_x * float(a) + per_y * float(c) + per_z * float(e)
                wp.atomic_add(grid_m, node, weight * mass)
                wp.atomic_add(grid_p, node, p_node * weight)

    def scattering(written: bool):
        @wp.kernel
        def scatter_all(w: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float), vectors: wp.array(dtype=wp.vec3),
                        base: wp.array(dtype=wp.vec3i), n_nodes: int, dims: wp.vec3i,
                        grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3)):
            i = wp.tid()
            group = i // 6  # a stencil's corner, pairs of threads on each of its planes
            a = i % 6 // 2
            offset = group % 2 * n_nodes
            corner = base[group]
            w_i = w[i]
            wy, wz = w[i + 1], w[i + 2]
            v = 4 * i
            if wp.static(written):
                # on a GPU a pair of lanes on one plane is a run (warp_reduce): they add once
                run = run_start((offset + kernels.node_index(corner[0], corner[1], corner[2], dims)) * 3 + a)
                kernels.scatter_plane(grid_m, grid_p, a, w_i[a], wy, wz, mass[i], vectors[v], vectors[v + 1],
                                      vectors[v + 2], vectors[v + 3], offset, corner, dims, run)
            else:
                plain(grid_m, grid_p, a, w_i[a], wy, wz, mass[i], vectors[v], vectors[v + 1], vectors[v + 2],
                      vectors[v + 3], offset, corner, dims)

        return scatter_all

    rng = np.random.default_rng(5)
    n, dims = 240, (6, 5, 7)
    G = int(np.prod(dims))

    def array(values, dtype):
        return wp.array(np.asarray(values, np.float32), dtype=dtype, device=DEVICE, requires_grad=True)

    values = {"w": rng.uniform(0.0, 1.0, size=(n + 2, 3)), "mass": rng.uniform(0.5, 2.0, size=n),
              "vectors": rng.normal(size=(4 * n, 3))}
    base = wp.array(rng.integers(0, np.array(dims) - 2, size=(n // 6, 3)).astype(np.int32), dtype=wp.vec3i,
                    device=DEVICE)
    node_grads = (rng.normal(size=2 * G), rng.normal(size=(2 * G, 3)))
    adjoints, grids = {}, {}
    for written in (False, True):
        inputs = {"w": array(values["w"], wp.vec3), "mass": array(values["mass"], float),
                  "vectors": array(values["vectors"], wp.vec3)}
        grid = (array(np.zeros(2 * G), float), array(np.zeros((2 * G, 3)), wp.vec3))
        tape = wp.Tape()
        with tape:
            wp.launch(scattering(written), n, inputs=[inputs["w"], inputs["mass"], inputs["vectors"], base, G,
                                                      wp.vec3i(*dims)], outputs=list(grid), device=DEVICE)
        grids[written] = [field.numpy().copy() for field in grid]
        for field, g in zip(grid, node_grads, strict=True):
            field.grad.assign(g.astype(np.float32))
        tape.backward()
        adjoints[written] = {name: array_.grad.numpy().copy() for name, array_ in inputs.items()}
    for plain_sum, written_sum, field in zip(grids[False], grids[True], grid, strict=True):
        assert np.allclose(written_sum, plain_sum, rtol=1e-5, atol=1e-6)
        # the backward pass replays the kernel without scattering again (Warp's replays the atomics)
        assert np.array_equal(field.numpy(), written_sum)
    for name, expected in adjoints[False].items():
        assert np.abs(expected).max() > 0, name
        assert np.allclose(adjoints[True][name], expected, rtol=1e-5, atol=1e-6 * np.abs(expected).max()), name
