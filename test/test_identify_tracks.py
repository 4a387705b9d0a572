"""The track loss of stage 3: attachment of surface tracks to particles, the loss, its gradient, and
the tracks' way from the frames into the fit problem."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from sim_scenes import scene

from mosiv_ros.config import updated
from mosiv_ros.identify.checkpoint import signature
from mosiv_ros.identify.fit import FitProblem, FitSettings, Identifier
from mosiv_ros.identify.losses import track_loss
from mosiv_ros.identify.observations import ATTACH_NEIGHBOURS, ATTACH_REACH, Observations, TrackAttachment
from mosiv_ros.sim import Ground, ObjectModel, Particles
from mosiv_ros.sim.sampling import box

RNG = np.random.default_rng(3)


def _two_blocks(spacing: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Particles of two touching blocks on a lattice: object 0 at x < 0.05, object 1 beyond."""
    grid = np.arange(0.0, 0.1, spacing) + spacing / 2
    x = np.stack(np.meshgrid(grid, grid[:5], grid[:5], indexing="ij"), axis=-1).reshape(-1, 3)
    return x, (x[:, 0] > 0.05).astype(int)


def _attached(frames: int = 3, spacing: float = 0.01):
    """Tracks on the blocks' faces (with one of them dead at frame 1), their attachment."""
    x0, objects = _two_blocks(spacing)
    faces = x0[RNG.choice(len(x0), 10, replace=False)] + RNG.normal(0, 0.2 * spacing, (10, 3))
    positions = np.repeat(faces[None], frames, axis=0) + np.arange(frames)[:, None, None] * 0.004
    positions[1, 2] = np.nan
    confidence = RNG.uniform(0.3, 1.0, (frames, 10))
    track_objects = (faces[:, 0] > 0.05).astype(int)
    attachment, dropped = TrackAttachment.attach(positions, confidence, track_objects, [0, 1], x0, objects,
                                                 spacing)
    assert dropped == 0 and attachment.n_tracks == 10
    return x0, objects, attachment


def test_tracks_attach_to_their_own_objects_nearest_particles_and_tracks_off_them_are_dropped():
    x0, objects = _two_blocks()
    # a track of object 0 right at the boundary: object 1's particles are as near, it takes its own
    at_boundary = np.array([0.0501, 0.025, 0.025])
    far = np.array([0.025, 0.025, 0.05 + ATTACH_REACH * 0.01 + 0.003])  # above the top layer's reach
    positions = np.stack([at_boundary, far, x0[7] + 0.001, x0[3]])[None]
    track_objects = np.array([0, 0, objects[7], -1])  # the last: an object the particles lack
    attachment, dropped = TrackAttachment.attach(positions, np.ones((1, 4)), track_objects, [0, 1], x0,
                                                 objects, 0.01)
    assert dropped == 2 and attachment.n_tracks == 2
    assert attachment.particles.shape == (2, ATTACH_NEIGHBOURS)
    assert np.all(objects[attachment.particles[0]] == 0) and np.all(objects[attachment.particles[1]] == objects[7])
    np.testing.assert_allclose(attachment.weights.sum(axis=1), 1.0)
    # inverse-distance weights: a track 1.7 mm from a particle (the others 8 mm and more) follows
    # it more than all the others together
    assert attachment.particles[1, 0] == 7 and attachment.weights[1, 0] > 0.5
    # the attached point starts on the track (the particles are inside the surface it is on)
    np.testing.assert_allclose(attachment.points(x0), positions[0, [0, 2]], atol=1e-15)
    # moving the particles moves the attached points with them (rigid translation)
    np.testing.assert_allclose(attachment.points(x0 + [0.1, 0, 0]), attachment.points(x0) + [0.1, 0, 0])
    # frames are sliced, the attachment to the first frame's particles stays
    later = TrackAttachment.attach(np.repeat(positions, 3, axis=0), np.ones((3, 4)), track_objects, [0, 1],
                                   x0, objects, 0.01)[0].select(slice(1, 3))
    assert later.positions.shape == (2, 2, 3) and np.array_equal(later.particles, attachment.particles)


def test_track_loss_is_the_confidence_weighted_pseudo_huber_mean_over_each_objects_tracks():
    x0, objects = _two_blocks()
    scale = 0.005
    track_objects = np.array([0, 0, 1])
    on = x0[[0, 1, len(x0) - 1]]  # each track exactly on a particle: it follows that particle alone
    offsets = np.array([[0.001, 0, 0], [0, 0.02, 0], [0, 0, 0.003]])
    positions = np.stack([on, on + offsets])
    confidence = np.array([[1.0, 1.0, 1.0], [0.5, 1.0, 0.8]])
    attachment, _ = TrackAttachment.attach(positions, confidence, track_objects, [0, 1], x0, objects, 0.01)
    total, _, per = track_loss(x0, attachment, 1, scale, 2)
    rho = scale**2 * (np.sqrt(1 + np.sum(offsets**2, axis=1) / scale**2) - 1)
    assert per[0] == pytest.approx((0.5 * rho[0] + rho[1]) / 2)
    assert per[1] == pytest.approx(0.8 * rho[2])
    assert total == pytest.approx(per.sum())
    # about |r|^2 / 2 well below the scale, about s |r| well above it: a drifted track's pull is bounded
    assert rho[0] == pytest.approx(0.001**2 / 2, rel=0.03)
    assert scale * 0.02 - scale**2 < rho[1] < scale * 0.02 < 0.02**2 / 2
    # at frame 0 every track is on its particle: nothing to pay
    assert track_loss(x0, attachment, 0, scale, 2)[0] == pytest.approx(0.0, abs=1e-20)


def test_track_loss_gradient_matches_finite_differences_and_a_dead_track_adds_nothing():
    x0, objects, attachment = _attached()
    x = x0 + RNG.normal(0, 0.003, x0.shape)
    for frame in (1, 2):
        loss, grad, per = track_loss(x, attachment, frame, 0.005, 2)
        assert loss == pytest.approx(per.sum()) and loss > 0
        h = 1e-7
        for i in {int(attachment.particles[t, j]) for t, j in [(0, 0), (3, 1), (7, 3), (9, 2)]}:
            for c in range(3):
                shifted = x.copy()
                shifted[i, c] += h
                up = track_loss(shifted, attachment, frame, 0.005, 2)[0]
                shifted[i, c] -= 2 * h
                down = track_loss(shifted, attachment, frame, 0.005, 2)[0]
                assert grad[i, c] == pytest.approx((up - down) / (2 * h), rel=1e-5, abs=1e-12)
        untouched = np.setdiff1d(np.arange(len(x)), attachment.particles[np.isfinite(
            attachment.positions[frame, :, 0])])
        assert not grad[untouched].any()
    # one track is dead at frame 1: moving the particles only it holds changes nothing
    dead = int(np.flatnonzero(np.isnan(attachment.positions[1, :, 0]))[0])
    only = np.setdiff1d(attachment.particles[dead], np.delete(attachment.particles, dead, axis=0))
    assert len(only)
    moved = x.copy()
    moved[only] += 0.05
    assert track_loss(moved, attachment, 1, 0.005, 2)[0] == track_loss(x, attachment, 1, 0.005, 2)[0]


def _dropped_cube(track_weight: float, chamfer_weight: float = 1.0, frames: int = 5):
    """A soft cube dropped on the ground, observed as its particles and tracked at its corners' particles."""
    dx = 0.02
    cube = box((0.2, 0.2, 0.14), (0.06, 0.06, 0.06), dx / 2)
    common = dict(dx=dx, lo=(0, 0, 0), hi=(0.4, 0.4, 0.3), frame_dt=1 / 30, ground=Ground(height=0.1, friction=0.5),
                  velocities=[(0.0, 0.0, -0.8)])
    truth = scene([cube], [ObjectModel("cube", "elastic", {"E": 1.5e4, "nu": 0.3})], **common)
    traj = truth.rollout(frames)[:, 0].astype(np.float64)
    x0 = cube[0]
    followed = np.argsort(np.linalg.norm(x0 - x0.mean(axis=0), axis=1))[-12:]  # the outermost particles
    positions = traj[:, followed] + 0.0005  # a little off them: weights over several particles
    attachment, _ = TrackAttachment.attach(positions, np.ones(positions.shape[:2]), np.ones(12, int), [1], x0,
                                           np.zeros(len(x0), int), dx / 2)
    obs = Observations(1 / 30, [[traj[f]] for f in range(frames + 1)], object_ids=[1], tracks=attachment)
    particles = Particles(x=x0, volume=cube[1], object_index=np.zeros(len(x0), int))
    problem = FitProblem([ObjectModel("cube", "elastic", {"E": 4e4, "nu": 0.3})], particles, obs, truth.config,
                         ["E"])
    settings = updated(FitSettings(), {"loss.track_weight": track_weight, "loss.chamfer_weight": chamfer_weight,
                                       "loss.silhouette_weight": 0.0})
    velocity = np.zeros((1, 6))
    velocity[0, 2] = -0.8
    return Identifier(problem, settings), velocity


def test_the_search_and_adam_score_the_same_track_term_and_its_gradient_through_the_simulation_is_exact():
    losses = {}
    for weight in (0.0, 1.0):
        identifier, velocity = _dropped_cube(weight)
        u = identifier.pack()
        identifier.apply(u, velocity)
        whole = identifier.window_loss(0, 5, None, grad=False)
        searched = identifier.search.batch_object_losses(u[None], velocity, together=False)
        assert searched[0][0] == pytest.approx(whole[0], rel=1e-6)
        np.testing.assert_allclose(searched[1][0], whole[3], rtol=1e-6)
        losses[weight] = whole[0]
    assert losses[1.0] > losses[0.0] * 1.05  # the track term is there, and not negligible
    # dL/dE of the track term alone (Chamfer off): the simulator's adjoint against a central difference
    identifier, velocity = _dropped_cube(1.0, chamfer_weight=0.0)
    u = identifier.pack()
    identifier.apply(u, velocity)
    _, du, _, _ = identifier.window_loss(0, 5, None, grad=True)
    values = []
    for sign in (1, -1):
        identifier.apply(u + sign * 1e-3, velocity)
        values.append(identifier.window_loss(0, 5, None, grad=False)[0])
    numeric = (values[0] - values[1]) / 2e-3
    assert numeric != 0.0 and du[0] == pytest.approx(numeric, rel=0.05)


def _frames_with_tracks(lose_tracks_at: tuple[int, ...] = ()):
    """Two resting cubes' observed frames, each cube's corner tracked; frame set 3 of 5 lost."""
    from mosiv_ros.lifting.lift import LiftedParticles
    from mosiv_ros.recon.reconstruct import ObjectGeometry, ObservedFrame
    from mosiv_ros.recon.tracks import TrackPoints

    cubes = {i: box((0.1 * i, 0.0, 0.05), (0.04, 0.04, 0.04), 0.01)[0] for i in (1, 2)}
    x = np.concatenate(list(cubes.values()))
    object_id = np.concatenate([np.full(len(c), i) for i, c in cubes.items()])
    lifted = LiftedParticles(x, object_id, object_id, np.zeros(len(x), np.uint8), np.full(len(x), -0.01),
                             1e-6, 5e3, 1e-4)
    corners = np.array([cubes[1].max(axis=0), cubes[2].max(axis=0), [5.0, 5.0, 5.0]])  # the last: off both
    frames = []
    for k in (0, 1, 2, 4):
        tracks = None if k in lose_tracks_at else TrackPoints(
            k * 100_000_000, corners + [0, 0, 0.001 * k], np.array([1, 2, 2], np.uint16),
            np.array([10, 11, 12], np.uint32), np.full(3, 0.9, np.float32))
        frames.append(ObservedFrame(k * 100_000_000, {i: ObjectGeometry(i, c, np.zeros((0, 3)), 0.01)
                                                      for i, c in cubes.items()}, tracks=tracks))
    from mosiv_ros.io.scene import Scene, SceneObject
    return frames, lifted, Scene([SceneObject(i, f"cube{i}", "elastic", {}) for i in (1, 2)])


def test_the_fit_problem_attaches_the_frames_tracks_and_a_lost_frame_has_none_alive(caplog):
    from mosiv_ros.identify.problem import ProblemOptions, build_problem

    frames, lifted, scene_ = _frames_with_tracks()
    with caplog.at_level(logging.INFO, logger="mosiv_ros"):
        problem = build_problem(frames, lifted, scene_, options=ProblemOptions(use_masks=False))
    tracks = problem.observations.tracks
    assert "surface tracks: 2 attached to the particles, 1 dropped" in caplog.text
    assert tracks.n_tracks == 2 and list(tracks.object_index) == [0, 1]
    assert tracks.positions.shape == (5, 2, 3)
    assert np.isnan(tracks.positions[3]).all() and np.isfinite(tracks.positions[[0, 1, 2, 4]]).all()
    assert tracks.positions[4, 0, 2] == pytest.approx(frames[3].tracks.xyz[0, 2])
    # the loop and the family choice slice the frames: the attachment stays with them
    assert problem.observations.select(slice(0, 3)).tracks.positions.shape == (3, 2, 3)
    # off (loss.track_weight 0), or no tracks at the first frame: no track term at all
    untracked = build_problem(frames, lifted, scene_, options=ProblemOptions(use_masks=False, use_tracks=False))
    assert untracked.observations.tracks is None
    # a checkpoint of the fit without tracks is not resumed by the fit with them
    assert signature(problem, ["E"], {}) != signature(untracked, ["E"], {})
    first_lost, _, _ = _frames_with_tracks(lose_tracks_at=(0,))
    assert build_problem(first_lost, lifted, scene_,
                         options=ProblemOptions(use_masks=False)).observations.tracks is None
    with pytest.raises(ValueError, match="3 track frames for 5 point frames"):
        Observations(0.1, problem.observations.points, [1, 2], tracks=tracks.select(slice(0, 3)))


def test_the_twins_track_error_is_the_distance_from_the_attached_points_on_fitted_and_held_out_frames():
    from mosiv_ros.evaluate.twin import track_errors
    from mosiv_ros.predict.twin import Prediction
    from mosiv_ros.recon.tracks import SurfaceTracks

    x0, objects = _two_blocks()
    frames = 6
    shift = np.arange(frames)[:, None, None] * np.array([0.01, 0.0, 0.0])
    prediction = Prediction(0, np.arange(frames) / 30, x0[None] + shift, objects, [4, 9], ["a", "b"])
    followed = [0, 1, len(x0) - 1]  # on particles: the attached point is the particle
    positions = x0[followed][None] + shift
    positions[:, 2, 1] += np.arange(frames) * 0.001  # object 9's track drifts 1 mm a frame off its particle
    positions[4, 0] = np.nan  # dead in a held-out frame
    far = np.full((frames, 1, 3), 5.0)  # off every particle: dropped
    tracks = SurfaceTracks(np.arange(frames), np.arange(4, dtype=np.uint32), np.array([4, 4, 9, 4], np.uint16),
                           np.concatenate([positions, far], axis=1), np.ones((frames, 4)))
    errors = track_errors(prediction, tracks, 3, 0.01)
    assert errors["attached"] == 3 and errors["dropped"] == 1
    observed = np.array([0, 0, 0.001, 0, 0, 0.002])  # frames 1 and 2
    future = np.array([0, 0, 0.003, 0, 0.004, 0, 0, 0.005])  # frames 3, 4 (track 0 dead), 5
    for part, values in (("observed", observed), ("future", future)):
        assert errors[part]["count"] == len(values)
        assert errors[part]["median"] == pytest.approx(np.median(values), abs=1e-9)
        assert errors[part]["rms"] == pytest.approx(np.sqrt(np.mean(values**2)))
