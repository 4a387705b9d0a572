"""Images of a recorded synthetic bag against the ground truth, through the bag's own calibration.

Every check reads the bag back (CameraInfo K, /tf_static extrinsics, /gripper/pose) and the
ground-truth sidecars, and recomputes what each pixel must show without the renderer's code.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from synth_scenes import FPS, PAIR

from mosiv_ros.io.bag import read_recording
from mosiv_ros.synth.ground_truth import read_ground_truth, read_ground_truth_particles

CLAY, BALL = 1, 2  # mask ids: objects in scene-file order
TOL = 2e-5  # m: float32 depth at < 1 m


@pytest.fixture(scope="module")
def pair(synth_pair_bag):
    return (read_recording(synth_pair_bag), read_ground_truth(synth_pair_bag),
            read_ground_truth_particles(synth_pair_bag))


def pixel_of(camera, point):
    """(row, col) of the pixel a world point projects to, through the camera's K and pose."""
    T = camera.T_world_optical
    u, v = camera.intrinsics.project((np.asarray(point, float) - T[:3, 3]) @ T[:3, :3])[0]
    return int(round(v)), int(round(u))


def world_rays(camera):
    """Camera centre and world directions (H*W, 3) of every pixel, optical z = 1 (ray parameter = depth)."""
    k = camera.intrinsics
    v, u = np.mgrid[0:k.height, 0:k.width]
    pixels = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
    R = camera.T_world_optical[:3, :3]
    return camera.T_world_optical[:3, 3], pixels @ np.linalg.inv(k.K).T @ R.T


def views(recording, particles):
    """(camera, frame, particle positions it shows): 'late' runs one frame ahead."""
    n = len(particles.positions)
    for name, camera in recording.cameras.items():
        shift = 1 if name == "late" else 0
        for k, frame in enumerate(camera.frames):
            if k + shift < n:
                yield camera, frame, particles.positions[k + shift]


def test_scene_file_points_project_onto_their_objects_mask_pixels_at_the_start(pair):
    recording, _, _ = pair
    ball = PAIR["objects"][1]["position"]
    clay_front = [0.0, -0.055, 0.015]  # just behind the slab's face towards the side cameras
    clay_corner = [0.06, 0.05, 0.045]  # just under the slab's top face, away from the ball
    for name in ("cam0", "cam1", "late"):
        mask = recording.cameras[name].frames[0].mask
        assert mask[pixel_of(recording.cameras[name], ball)] == BALL, name
        assert mask[pixel_of(recording.cameras[name], clay_front)] == CLAY, name
    top = recording.cameras["top"].frames[0].mask
    assert top[pixel_of(recording.cameras["top"], clay_corner)] == CLAY


def test_nearer_object_owns_the_pixel_where_the_view_lines_up_two_objects(pair):
    recording, _, _ = pair
    top = recording.cameras["top"]  # straight down: the ball hides the slab's centre
    row, col = pixel_of(top, PAIR["objects"][0]["position"])
    assert top.frames[0].mask[row, col] == BALL
    slab_top = 0.05
    assert top.frames[0].depth[row, col] < top.T_world_optical[2, 3] - slab_top - 0.05


def test_mask_and_depth_show_the_nearest_ground_truth_particle_ball_on_every_ray(pair):
    recording, truth, particles = pair
    r = truth["render"]["splat_radius"]
    checked = 0
    for camera, frame, x in views(recording, particles):
        origin, rays = world_rays(camera)
        mask, depth = frame.mask.ravel(), frame.depth.ravel().astype(np.float64)
        tree = cKDTree(x)
        on_object = mask > 0
        points = origin + depth[on_object, None] * rays[on_object]
        distance, nearest = tree.query(points)
        # on the surface of a ball of the pixel's own object, inside no ball
        assert np.all(np.abs(distance - r) < TOL)
        assert np.all(particles.object_id[nearest] == mask[on_object])
        # everything else: no object ball comes closer than r to the ray before its hit (or ever)
        others = np.flatnonzero(~on_object)
        reach = np.where(np.isfinite(depth[others]), depth[others], np.inf)
        for chunk in np.array_split(others, 8):
            d = rays[chunk]
            s = np.clip(((x - origin) @ d.T) / np.einsum("ij,ij->i", d, d), 0.0, reach[np.searchsorted(others, chunk)])
            closest = origin + s.T[:, :, None] * d[:, None, :]
            gap = np.linalg.norm(closest - x[None], axis=2)
            assert gap.min() > r - TOL
        checked += 1
    assert checked == 4 * 6 - 1  # every camera and frame, 'late' but its last


def test_pixels_of_no_object_lie_on_the_floor_or_the_gripper(pair):
    recording, truth, _ = pair
    r = truth["render"]["splat_radius"]
    radius = PAIR["gripper"]["radius"]
    gripper = dict(recording.gripper_poses)
    for name in ("cam0", "cam1", "top"):
        camera = recording.cameras[name]
        origin, rays = world_rays(camera)
        for frame in camera.frames:
            depth = frame.depth.ravel()
            hit = (frame.mask.ravel() == 0) & np.isfinite(depth)
            points = origin + depth[hit, None].astype(np.float64) * rays[hit]
            on_floor = np.abs(points[:, 2]) < TOL
            on_gripper = np.linalg.norm(points - gripper[frame.stamp_ns][:3, 3], axis=1) < radius + r + TOL
            assert np.all(on_floor | on_gripper)
            assert on_floor.mean() > 0.5


def test_object_pixels_are_shaded_versions_of_the_object_colour(pair):
    recording, _, _ = pair
    colors = {CLAY: np.array(PAIR["objects"][0]["color"], float), BALL: np.array(PAIR["objects"][1]["color"], float)}
    for camera in recording.cameras.values():
        for frame in camera.frames:
            for object_id, color in colors.items():
                rgb = frame.rgb[frame.mask == object_id].astype(float)
                scale = rgb @ color / (color @ color)
                assert np.all(np.abs(rgb - scale[:, None] * color) <= 1.5)
                assert np.all((scale > 0.1) & (scale <= 1.0 + 1e-9))


def test_a_camera_with_a_time_offset_shows_the_scene_later_under_the_same_stamps(pair):
    recording, truth, _ = pair
    cam0, late = recording.cameras["cam0"], recording.cameras["late"]
    assert late.stamps_ns == cam0.stamps_ns
    assert np.array_equal(late.T_world_optical, cam0.T_world_optical)
    offset = next(e for e in truth["effects"] if e["type"] == "camera_time_offset")["params"]["offset"]
    assert offset * FPS == pytest.approx(1.0)
    for k in range(len(cam0.frames) - 1):
        assert np.array_equal(late.frames[k].rgb, cam0.frames[k + 1].rgb)
        assert np.array_equal(late.frames[k].mask, cam0.frames[k + 1].mask)
        assert np.array_equal(late.frames[k].depth, cam0.frames[k + 1].depth, equal_nan=True)
    assert not np.array_equal(late.frames[0].mask, cam0.frames[0].mask)  # the scene does move
