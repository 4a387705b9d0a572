"""Synthetic camera rigs: placements look at their target, pixel rays match the projection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mosiv_ros.synth.cameras import hemisphere_poses, look_at, pinhole, pixel_rays, ring_poses

TARGET = np.array([0.1, -0.2, 0.05])


def optical(T, point):
    return (np.asarray(point, float) - T[:3, 3]) @ T[:3, :3]


def test_ring_cameras_stand_on_their_circle_and_see_the_target_at_the_principal_point():
    K = pinhole(80, 60, horizontal_fov=1.0)
    poses = ring_poses(5, 0.7, 0.4, TARGET, start_angle=0.2)
    for i, T in enumerate(poses):
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
        assert T[2, 3] == pytest.approx(0.4)
        assert np.hypot(*(T[:2, 3] - TARGET[:2])) == pytest.approx(0.7)
        assert math.atan2(T[1, 3] - TARGET[1], T[0, 3] - TARGET[0]) == pytest.approx(
            math.remainder(0.2 + 2 * math.pi * i / 5, 2 * math.pi))
        assert K.project(optical(T, TARGET))[0] == pytest.approx(K.K[:2, 2])
        assert T[2, 0] == pytest.approx(0.0, abs=1e-12)  # image x stays level with the horizon
        assert optical(T, TARGET + [0.0, 0.0, 0.1])[1] < 0  # world up is image up (optical y down)


def test_hemisphere_cameras_spread_between_their_elevations_at_one_distance():
    poses = hemisphere_poses(7, 1.2, TARGET, 0.3, 1.2)
    elevations = [math.asin((T[2, 3] - TARGET[2]) / 1.2) for T in poses]
    for T in poses:
        assert np.linalg.norm(T[:3, 3] - TARGET) == pytest.approx(1.2)
        assert optical(T, TARGET)[:2] == pytest.approx([0.0, 0.0], abs=1e-12)
    assert 0.3 <= min(elevations) and max(elevations) <= 1.2 and len({round(e, 6) for e in elevations}) == 7


def test_a_camera_looking_straight_down_is_still_a_proper_rotation():
    T = look_at([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0) and T[:3, 2] == pytest.approx([0.0, 0.0, -1.0])
    with pytest.raises(ValueError, match="cannot look at its own position"):
        look_at([1.0, 1.0, 1.0], [1.0, 1.0, 1.0])


def test_pixel_rays_are_the_inverse_of_the_projection():
    K = pinhole(40, 30, fx=50.0, fy=45.0, cx=19.0, cy=16.0)
    rays = pixel_rays(K)
    assert rays[:, 2] == pytest.approx(np.ones(40 * 30))
    v, u = np.divmod(np.arange(40 * 30), 40)
    assert K.project(rays * 2.5) == pytest.approx(np.stack([u, v], axis=1))
