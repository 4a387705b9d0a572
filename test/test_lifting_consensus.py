"""Stage 2's temporal consensus: hull that later frames do not hold is cut before lifting."""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import numpy as np
from test_lifting_particles import FINE, SCENE, VOXEL, ball, observed, voxelised

from mosiv_ros.io.recording import PointCloud
from mosiv_ros.lifting import lift

RADIUS = 0.03
CENTRE = np.array([0.01, -0.02, 0.1])
STEP = np.array([0.0123, -0.0071, 0.0214])  # per frame: not a whole number of voxels
PHANTOM = (np.array([0.035, -0.025, 0.095]), np.array([0.06, -0.01, 0.11]))  # sticks out of the ball
SAND = np.array([0.2, 0.0, 0.05])


def slab(lo, hi) -> np.ndarray:
    return voxelised(lambda p: np.all((p >= lo) & (p <= hi), axis=1), lo, hi)


def at(stamp: int, *objects: np.ndarray) -> PointCloud:
    cloud = observed(*objects)
    cloud.stamp_ns = stamp
    return cloud


def in_phantom(x: np.ndarray) -> np.ndarray:
    """Points of the slab beyond the one voxel of slack that consensus allows around the ball."""
    inside = np.all((x >= PHANTOM[0]) & (x <= PHANTOM[1]), axis=1)
    return inside & (np.linalg.norm(x - CENTRE, axis=1) > RADIUS + 2 * VOXEL)


def test_hull_that_later_frames_do_not_hold_is_cut_and_the_moving_body_kept_whole():
    hidden = np.unique(np.concatenate([ball(CENTRE, RADIUS), slab(*PHANTOM)]), axis=0)
    first = at(0, hidden, ball(SAND, 0.02))
    # The ball flies on without its phantom; the second object is missing from the last frame.
    later = [at(1, ball(CENTRE + STEP, RADIUS), ball(SAND, 0.02)), at(2, ball(CENTRE + 2 * STEP, RADIUS))]
    plain = lift(first, replace(FINE, consensus_frames=0), SCENE, later)
    trimmed = lift(first, FINE, SCENE, later)
    solid = (trimmed.object_id == 1) & (trimmed.sdf <= 0)
    assert in_phantom(plain.x[(plain.object_id == 1) & (plain.sdf <= 0)]).sum() > 20
    assert not in_phantom(trimmed.x[solid]).any()
    true = 4 / 3 * math.pi * RADIUS**3
    assert abs(trimmed.object_volume(1) / true - 1) < 0.03
    # Every particle of the ball itself is still there.
    body = np.linalg.norm(plain.x - CENTRE, axis=1) < RADIUS - FINE.particle_spacing
    kept = {tuple(p) for p in np.round(trimmed.x[solid] / FINE.particle_spacing).astype(int)}
    assert all(tuple(p) in kept for p in np.round(plain.x[body] / FINE.particle_spacing).astype(int))
    # An object a later frame does not show is left as it was.
    assert np.isclose(trimmed.object_volume(2), plain.object_volume(2))
    assert trimmed.warnings == []


def test_a_later_frame_in_which_the_object_deformed_is_not_used_and_is_named(caplog):
    first = at(0, ball(CENTRE, RADIUS))
    squashed = voxelised(lambda p: np.sum(((p - CENTRE) / [1.6 * RADIUS, 1.6 * RADIUS, 0.35 * RADIUS]) ** 2,
                                          axis=1) <= 1, CENTRE - 1.6 * RADIUS, CENTRE + 1.6 * RADIUS)
    later = [at(5, squashed)]
    with caplog.at_level(logging.INFO, logger="mosiv_ros.lifting.consensus"):
        lifted = lift(first, FINE, SCENE, later)
    unchanged = lift(first, replace(FINE, consensus_frames=0), SCENE)
    np.testing.assert_array_equal(lifted.x, unchanged.x)
    assert "object 1: its hull at stamp 5 ns" in caplog.text and "not used" in caplog.text


def test_only_the_configured_number_of_later_frames_is_used():
    hidden = np.unique(np.concatenate([ball(CENTRE, RADIUS), slab(*PHANTOM)]), axis=0)
    later = [at(1, hidden), at(2, ball(CENTRE, RADIUS))]  # the phantom stays for one frame
    one = lift(at(0, hidden), replace(FINE, consensus_frames=1), SCENE, later)
    two = lift(at(0, hidden), FINE, SCENE, later)
    assert in_phantom(one.x[one.sdf <= 0]).any()
    assert not in_phantom(two.x[two.sdf <= 0]).any()
