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


def test_balls_that_graze_the_lens_or_lie_beyond_the_image_edge_are_drawn_as_exact_ray_casts():
    """The renderer's footprints against a ray cast of every pixel through every ball.

    One ball sits just in front of the lens (it covers the whole image: a full-suite ball that
    flew past a camera made the unclipped footprint run out of memory); one is centred far left
    of the image but reaches into it; the rest are ordinary.
    """
    from mosiv_ros.io.recording import CameraIntrinsics
    from mosiv_ros.synth.render import Splats, render_view

    w, h, r = 40, 30, 0.02
    intrinsics = CameraIntrinsics(w, h, [[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]])
    rng = np.random.default_rng(3)
    ordinary = np.column_stack([rng.uniform(-0.3, 0.3, 30), rng.uniform(-0.2, 0.2, 30), rng.uniform(0.5, 1.0, 30)])
    cases = {"grazing": np.array([[0.01, 0.0, r * (1 + 1e-5)]]), "beyond the edge": np.array([[-0.03, 0.0, 0.03]])}
    for name, special in cases.items():
        x = np.vstack([special, ordinary])  # the optical frame is the world frame
        labels = np.r_[1, np.full(len(ordinary), 2)]
        splats = Splats(x, labels, np.full((len(x), 3), 200.0), np.tile([0.0, 0.0, -1.0], (len(x), 1)), r)
        _, mask, depth = render_view(intrinsics, np.eye(4), splats, None)
        v, u = np.mgrid[0:h, 0:w]
        d = np.stack([(u.ravel() - 19.5) / 50.0, (v.ravel() - 14.5) / 50.0, np.ones(u.size)], axis=1)
        a = np.einsum("ij,ij->i", d, d)[:, None]
        b = d @ x.T
        disc = b * b - a * (np.einsum("ij,ij->i", x, x) - r * r)[None]
        s = np.where((disc >= 0) & (b > 0), (b - np.sqrt(np.clip(disc, 0, None))) / a, np.inf)
        nearest = s.min(axis=1)
        expected_mask = np.where(np.isfinite(nearest), labels[s.argmin(axis=1)], 0)
        assert np.array_equal(mask.ravel(), expected_mask), name
        seen = np.isfinite(nearest)
        np.testing.assert_allclose(depth.ravel()[seen], nearest[seen], rtol=1e-6, err_msg=name)
        assert np.all(np.isnan(depth.ravel()[~seen])), name
        assert (mask.ravel() == 1).sum() > (w * h if name == "grazing" else 20) - 1, name
