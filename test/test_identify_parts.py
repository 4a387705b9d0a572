"""The identifier's parts through their own interfaces: search, curriculum (Adam), checkpoint."""

from __future__ import annotations

import json
import logging
from dataclasses import replace

import numpy as np
import pytest
from sim_scenes import DEVICE
from test_identify import _cube_problem

from mosiv_ros.config import updated
from mosiv_ros.identify.checkpoint import CHECKPOINT_FILE, SEARCH_FILE, Checkpoint, signature
from mosiv_ros.identify.curriculum import Adam, FitState, window_starts
from mosiv_ros.identify.fit import Identifier
from mosiv_ros.identify.run import build_kernels_aside
from mosiv_ros.identify.search import SEARCH_RANGES
from mosiv_ros.sim import SimState


def test_adams_first_step_is_the_learning_rate_against_the_gradients_sign_and_undo_takes_it_back():
    adam = Adam(np.array([0.1, 0.2, 0.3]))
    step = adam.step(np.array([4.0, -0.5, np.nan]))  # a NaN gradient moves nothing
    # bias-corrected moments of one gradient g: m = g, v = g^2, so the step is -lr g / |g|
    np.testing.assert_allclose(step, [-0.1, 0.2, 0.0], rtol=1e-9)
    # the second: m = 0.1 g1 + 0.09 g2 over 0.19, v likewise with squares over 0.001999
    g1, g2 = 4.0, 1.0
    m = (0.1 * 0.9 * g1 + 0.1 * g2) / (1 - 0.9**2)
    v = (0.001 * 0.999 * g1**2 + 0.001 * g2**2) / (1 - 0.999**2)
    assert adam.step(np.array([g2, 0.0, 0.0]))[0] == pytest.approx(-0.1 * m / np.sqrt(v), rel=1e-9)
    u, velocity = np.array([1.0]), np.array([[2.0, 3.0]])
    moved_u = u + adam.last[:1]
    moved_velocity = velocity + adam.last[1:].reshape(1, 2)
    back_u, back_velocity = adam.undo(moved_u, moved_velocity)
    np.testing.assert_allclose(back_u, u)
    np.testing.assert_allclose(back_velocity, velocity)
    assert not adam.last.any()  # nothing left to undo


def test_windows_spread_over_the_sequence_and_the_whole_one_starts_at_frame_zero():
    assert window_starts(20, 5, 3) == [0, 8, 15]
    assert window_starts(20, 18, 5) == [0, 1, 2]  # no more windows than starting frames
    assert window_starts(20, 20, 3) == [0]
    assert window_starts(20, 5, 1) == [0]


def _state(rng: np.random.Generator, n_entries: int = 2) -> FitState:
    adam = Adam(np.full(n_entries + 6, 0.05))
    adam.step(rng.normal(size=n_entries + 6))
    return FitState(rng.normal(size=n_entries), rng.normal(size=(1, 6)), adam,
                    (rng.normal(size=n_entries), rng.normal(size=(1, 6))),
                    (0.25, rng.normal(size=n_entries), rng.normal(size=(1, 6)), np.array([0.25])),
                    [{"stage": 0, "loss": 0.5, "values": {"cube.E": 1e4}}], 1, 3, 2)


def test_a_checkpoint_reads_back_the_state_it_saved_and_only_for_its_own_fit(tmp_path, caplog):
    state = _state(np.random.default_rng(1))
    Checkpoint(str(tmp_path), "fit-a").save(state)
    loaded = Checkpoint(str(tmp_path), "fit-a").load()
    for name in ("u", "velocity"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(state, name))
    for got, saved in zip([*loaded.start, *loaded.best], [*state.start, *state.best], strict=True):
        np.testing.assert_array_equal(got, saved)
    for name in ("m", "v", "lr"):
        np.testing.assert_array_equal(getattr(loaded.adam, name), getattr(state.adam, name))
    assert loaded.adam.t == state.adam.t == 1
    assert (loaded.history, loaded.stage, loaded.iteration, loaded.failures) == \
        (state.history, 1, 3, 2)
    with caplog.at_level(logging.WARNING):
        assert Checkpoint(str(tmp_path), "fit-b").load() is None
    assert "belongs to another problem or settings" in caplog.text
    (tmp_path / CHECKPOINT_FILE).write_bytes((tmp_path / CHECKPOINT_FILE).read_bytes()[:100])
    assert Checkpoint(str(tmp_path), "fit-a").load() is None  # cut short: afresh
    assert Checkpoint(str(tmp_path / "none"), "fit-a").load() is None
    Checkpoint("", "fit-a").save(state)  # no directory: nothing kept
    assert Checkpoint("", "fit-a").load() is None


def test_a_searchs_checkpoint_reads_back_its_rounds_only_for_its_own_fit_and_goes_with_the_first_state(
        tmp_path, caplog):
    rounds = [{"kept": [([0.1, -2.5], 3.2e-4), ([0.3, 1e-17], float("inf"))],
               "sampler": np.random.default_rng(0).bit_generator.state}]
    Checkpoint(str(tmp_path), "fit-a").save_search(rounds)
    loaded = Checkpoint(str(tmp_path), "fit-a").load_search()
    assert [[(list(u), value) for u, value in r["kept"]] for r in loaded] == \
        [[(u, value) for u, value in r["kept"]] for r in rounds]  # floats to the bit, inf too
    rng = np.random.default_rng()
    rng.bit_generator.state = loaded[0]["sampler"]
    assert rng.random() == np.random.default_rng(0).random()
    with caplog.at_level(logging.WARNING):
        assert Checkpoint(str(tmp_path), "fit-b").load_search() == []
        (tmp_path / SEARCH_FILE).write_text((tmp_path / SEARCH_FILE).read_text()[:40])
        assert Checkpoint(str(tmp_path), "fit-a").load_search() == []  # cut short: afresh
    assert "belongs to another problem" in caplog.text and "cannot read the search's checkpoint" in caplog.text
    Checkpoint(str(tmp_path), "fit-a").save(_state(np.random.default_rng(1)))
    assert not (tmp_path / SEARCH_FILE).exists()
    Checkpoint("", "fit-a").save_search(rounds)  # no directory: nothing kept
    assert Checkpoint("", "fit-a").load_search() == []


def test_a_fits_signature_changes_with_its_problem_and_result_settings_only():
    problem, settings = _cube_problem({"E": 2e4}, {"E": 5e3}, ["E"], frames=3)
    labels = Identifier(problem, settings).entries
    base = signature(problem, [e.label for e in labels], settings.result_settings())
    same = signature(problem, [e.label for e in labels],
                     replace(settings, cpu_workers=1, checkpoint_dir="elsewhere").result_settings())
    assert same == base
    assert signature(problem, [e.label for e in labels],
                     updated(settings, {"curriculum.iterations": 7}).result_settings()) != base
    assert signature(problem, ["cube.nu"], settings.result_settings()) != base
    shorter, _ = _cube_problem({"E": 2e4}, {"E": 5e3}, ["E"], frames=2)
    assert signature(shorter, [e.label for e in labels], settings.result_settings()) != base


@pytest.mark.skipif(DEVICE != "cpu", reason="losses to the bit, and the CPU's scoring: each row alone at its own step")
def test_the_search_keeps_the_candidate_of_lowest_loss_and_samples_the_prior_range():
    problem, settings = _cube_problem({"E": 2e4, "nu": 0.3}, {"E": 6e4, "nu": 0.3}, ["E"], frames=6,
                                      cpu_workers=1)
    identifier = Identifier(problem, settings)
    search = identifier.search
    velocity = np.zeros((1, 6))
    velocity[0, :3] = problem.observations.initial_velocities()
    coordinate = identifier.entries[0].coordinate
    lo, hi = search.box(identifier.pack())
    np.testing.assert_allclose([lo[0], hi[0]], [coordinate.to_u(v) for v in SEARCH_RANGES["E"]])
    current = identifier.pack()
    candidates = np.array([[coordinate.to_u(E)] for E in (4e3, 1.5e4, 2.5e4, 2e5)])
    kept = search.best(current, candidates, velocity, [[0]], keep=2)
    losses = search.batch_losses(np.vstack([current[None], candidates]), velocity, together=False)
    order = np.argsort(losses)
    assert [float(u[0]) for u, _ in kept] == [float(np.vstack([current[None], candidates])[i, 0])
                                              for i in order[:2]]
    assert [loss for _, loss in kept] == [losses[i] for i in order[:2]]
    best_E = float(coordinate.to_theta(kept[0][0][0]))
    assert min(abs(best_E / E - 1) for E in (1.5e4, 2.5e4)) < 1e-9  # one either side of the true 20 kPa


@pytest.mark.skipif(DEVICE != "cpu", reason="losses to the bit, and the CPU's scoring: each row alone at its own step")
def test_a_known_loss_of_the_current_point_ranks_the_contenders_as_scoring_it_again_does():
    problem, settings = _cube_problem({"E": 2e4, "nu": 0.3}, {"E": 6e4, "nu": 0.3}, ["E"], frames=4)
    search = Identifier(problem, settings).search
    velocity = np.zeros((1, 6))
    velocity[0, :3] = problem.observations.initial_velocities()
    coordinate = search.identifier.entries[0].coordinate
    current = np.array([coordinate.to_u(3e4)])
    candidates = np.array([[coordinate.to_u(E)] for E in (4e3, 1.5e4, 2.5e4, 2e5)])
    scored = [(u.tolist(), loss) for u, loss in search.best(current, candidates, velocity, [[0]], keep=3)]
    known = search.batch_losses(current[None], velocity, together=False)[0]
    assert [(u.tolist(), loss) for u, loss in search.best(current, candidates, velocity, [[0]], keep=3,
                                                          current_loss=known)] == scored


def _rows_scored(search, monkeypatch) -> list[int]:
    """The row counts of ``search``'s batched-loss calls from now on (the calls run as before)."""
    rows = []
    scored = search.batch_object_losses

    def counted(points, *args, **kwargs):
        rows.append(len(points))
        return scored(points, *args, **kwargs)

    monkeypatch.setattr(search, "batch_object_losses", counted)
    return rows


@pytest.mark.skipif(DEVICE != "cpu", reason="losses to the bit, and the CPU's scoring: each row alone at its own step")
def test_on_the_cpu_the_best_candidates_are_not_rolled_out_again_as_contenders(monkeypatch):
    problem, settings = _cube_problem({"E": 2e4, "nu": 0.3}, {"E": 6e4, "nu": 0.3}, ["E", "nu"], frames=4)
    search = Identifier(problem, settings).search
    velocity = np.zeros((1, 6))
    velocity[0, :3] = problem.observations.initial_velocities()
    E, nu = (e.coordinate for e in search.identifier.entries)
    current = np.array([E.to_u(3e4), nu.to_u(0.3)])
    candidates = np.array([[E.to_u(value), nu.to_u(0.25)] for value in (4e3, 1.5e4, 2.5e4, 2e5)])
    rows = _rows_scored(search, monkeypatch)
    kept = search.best(current, candidates, velocity, [[0, 1]], keep=3)
    assert rows == [4, 1]  # the candidates, then the current point alone (the composite is the best)
    points = np.vstack([current[None], candidates])
    alone = search.batch_losses(points, velocity, together=False)
    order = np.argsort(alone)[:3]
    assert [(u.tolist(), loss) for u, loss in kept] == [(points[i].tolist(), alone[i]) for i in order]
    rows.clear()
    again = search.best(current, candidates, velocity, [[0, 1]], keep=3, current_loss=alone[0])
    assert rows == [4]  # every contender's loss known
    assert [(u.tolist(), loss) for u, loss in again] == [(points[i].tolist(), alone[i]) for i in order]


@pytest.mark.skipif(DEVICE != "cpu", reason="losses to the bit, and the CPU's scoring: each row alone at its own step")
def test_rounds_side_by_side_score_their_contenders_in_one_batch_and_end_as_each_alone(monkeypatch):
    problem, settings = _cube_problem({"E": 2e4, "nu": 0.3}, {"E": 6e4, "nu": 0.3}, ["E"], frames=4)
    search = Identifier(problem, settings).search
    velocity = np.zeros((1, 6))
    velocity[0, :3] = problem.observations.initial_velocities()
    coordinate = search.identifier.entries[0].coordinate
    rounds = [(np.array([coordinate.to_u(E)]), np.array([[coordinate.to_u(c)] for c in candidates]), None)
              for E, candidates in ((3e4, (4e3, 1.5e4, 2.5e4)), (8e3, (6e3, 1e4, 1.8e4)))]
    alone = [search.best(current, candidates, velocity, [[0]], keep=2) for current, candidates, _ in rounds]
    rows = _rows_scored(search, monkeypatch)
    together = search.best_of(rounds, velocity, [[0]], keep=2)
    assert rows == [3, 3, 2]  # each round's candidates, then both current points in one batch
    assert [[(u.tolist(), loss) for u, loss in found] for found in together] == \
        [[(u.tolist(), loss) for u, loss in found] for found in alone]


@pytest.mark.skipif(DEVICE != "cpu", reason="a search repeated to the bit: a GPU's float atomics may tip a choice")
def test_a_search_checkpoint_of_an_earlier_layout_resumes_from_its_first_round(tmp_path, caplog):
    options = {"search.samples": 4, "search.starts": 2, "search.rounds": 1, "curriculum.iterations": 1,
               "curriculum.horizons": [0]}
    problem, settings = _cube_problem({"E": 2e4, "nu": 0.3}, {"E": 6e4, "nu": 0.3}, ["E"], frames=3,
                                      checkpoint_dir=str(tmp_path), **options)
    velocity = np.zeros((1, 6))
    velocity[0, :3] = problem.observations.initial_velocities()
    reference = Identifier(problem, replace(settings, checkpoint_dir="")).search.run(velocity)
    identifier = Identifier(problem, settings)
    checkpoint = Checkpoint(str(tmp_path), "fit")
    identifier.search.run(velocity, checkpoint)
    rounds = json.loads((tmp_path / SEARCH_FILE).read_text())["rounds"]
    assert [sorted(r) for r in rounds] == [["kept", "sampler"], ["starts"]]
    # a later round as an earlier version kept it: one start's points, and the sampler's state
    checkpoint.save_search([rounds[0], {"kept": rounds[1]["starts"][0], "sampler": rounds[0]["sampler"]}])
    with caplog.at_level(logging.INFO, logger="mosiv_ros.identify.search"):
        resumed = Identifier(problem, settings).search.run(velocity, checkpoint)
    assert "1 rounds done" in caplog.text
    assert [loss for _, loss in resumed] == [loss for _, loss in reference]
    for (u, _), (u_reference, _) in zip(resumed, reference, strict=True):
        np.testing.assert_array_equal(u, u_reference)


@pytest.mark.skipif(DEVICE != "cpu", reason="losses to the bit, and the CPU's scoring: each row alone at its own step")
def test_the_fits_end_points_score_side_by_side_as_each_alone_on_the_fits_simulator():
    problem, settings = _cube_problem({"E": 2e4, "nu": 0.3}, {"E": 6e4, "nu": 0.3}, ["E", "nu"], frames=4)
    identifier = Identifier(problem, settings)
    velocity = np.zeros((1, 6))
    velocity[0, :3] = problem.observations.initial_velocities()
    points = [(identifier.pack() + shift, velocity + 0.1 * shift) for shift in (0.0, 0.3, -0.2)]
    alone = []
    for u, v in points:
        identifier.apply(u, v)
        loss, _, _, per = identifier.window_loss(0, 4, None, grad=False)
        alone.append((loss, per))
    together = identifier._whole_window(points)
    assert [(loss, per.tolist()) for loss, per in together] == [(loss, per.tolist()) for loss, per in alone]


def test_a_resynchronised_window_starts_on_the_observed_centroid_and_its_velocity():
    problem, settings = _cube_problem({"E": 2e4}, {"E": 5e3}, ["E"], frames=6)
    identifier = Identifier(problem, settings)
    identifier.apply(identifier.pack(), np.zeros((1, 6)))  # dropped at rest: off the observations
    anchor = identifier.curriculum.anchor([0, 3])
    assert sorted(anchor) == [3]
    state = identifier.curriculum.resynced(anchor, 3)
    assert isinstance(state, SimState)
    observed = identifier.observed_centroids
    np.testing.assert_allclose(state.x[0].mean(axis=0), observed[3, 0], atol=1e-6)
    dt = problem.observations.frame_dt
    np.testing.assert_allclose(state.v[0].mean(axis=0), (observed[4, 0] - observed[2, 0]) / (2 * dt),
                               atol=1e-5)
    # the anchor's own state is left as it was: its centroid is elsewhere
    assert np.linalg.norm(anchor[3].x[0].mean(axis=0) - observed[3, 0]) > 1e-3


def test_the_initial_velocity_passes_over_frames_the_stream_lost_and_keeps_a_resting_object_at_rest():
    from mosiv_ros.identify.observations import Observations

    dt, v0, g = 1 / 30, np.array([1.2, -0.3, 2.0]), np.array([0.0, 0.0, -9.81])
    rng = np.random.default_rng(3)
    shape = rng.normal(scale=0.02, size=(200, 3))
    shape -= shape.mean(axis=0)
    points = []
    for f in range(10):
        t = f * dt
        thrown = shape + v0 * t + 0.5 * g * t**2
        resting = shape + [0.3, 0.0, 0.02] + rng.normal(scale=3e-4, size=3)  # a hull's jitter
        points.append([thrown, resting])
    for lost in (1, 2, 3):  # the stream lost these frames: no points of either object
        points[lost] = [np.zeros((0, 3)), np.zeros((0, 3))]
    velocity = Observations(dt, points, [1, 2]).initial_velocities()
    np.testing.assert_allclose(velocity[0], v0, atol=1e-9)
    np.testing.assert_array_equal(velocity[1], 0.0)
    # past the horizon nothing is guessed: an object seen once in it keeps zero
    assert not Observations(dt, points[:1] + [[np.zeros((0, 3))] * 2] * 9, [1, 2]).initial_velocities().any()


def test_kernels_built_aside_are_the_ones_a_fit_loads_and_a_failed_build_is_only_logged(caplog):
    # identify_node and `mosiv run` build them while the recording arrives: afterwards the fit's
    # own loads (the simulator's modules and the losses') find every module loaded already
    import subprocess
    import sys

    code = ("import logging, sys; logging.basicConfig(level=logging.INFO, stream=sys.stdout); "
            "from mosiv_ros.identify.run import build_kernels_aside; "
            f"build_kernels_aside({DEVICE!r}).join(); print('built aside'); "
            "from mosiv_ros.identify import losses; from mosiv_ros.sim import runtime; "
            "from mosiv_ros.sim.simulator import load_kernels; "
            f"load_kernels({DEVICE!r}); runtime.load_modules({DEVICE!r}, [losses])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600,
                         check=True).stdout
    before, after = out.split("built aside")
    assert f"kernels ready on {DEVICE}" in before
    assert "loading the simulator's kernels" not in after  # nothing left for the fit to build
    with caplog.at_level(logging.WARNING):
        build_kernels_aside("cuda:99").join(timeout=60)
    assert "building the kernels ahead of the fit failed (the fit will try again)" in caplog.text
    assert "cuda:99" in caplog.text
