"""The declared gripper in stage 1: where it hides the objects, the space it fills, its pose at a stamp."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from mosiv_ros.config import ReconstructionConfig
from mosiv_ros.io.bag import read_recording
from mosiv_ros.io.recording import Camera, Frame, match_frames
from mosiv_ros.io.scene import DeclaredGripper
from mosiv_ros.metrics import chamfer_distance
from mosiv_ros.recon import Reconstructor
from mosiv_ros.recon.gripper import GripperShape, gripper_at
from mosiv_ros.recon.views import OCCLUDED, View
from mosiv_ros.synth.ground_truth import read_ground_truth_particles
from mosiv_ros.synth.shapes import ring_camera_pose, ring_intrinsics

PRESSED = Path(__file__).resolve().parents[1] / "bags" / "pressed_cube"


def _view() -> View:
    intrinsics = ring_intrinsics(160, 120)
    camera = Camera("cam", intrinsics, ring_camera_pose(0, 4))
    blank = Frame(0, np.zeros((120, 160, 3), np.uint8), np.zeros((120, 160), np.uint16))
    return View(camera, blank, mask_filter=1, use_depth=False)


def _pose(position, rotation=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rotation).as_matrix()
    T[:3, 3] = position
    return T


@pytest.mark.parametrize("declared", [DeclaredGripper("sphere", (0.06,)),
                                      DeclaredGripper("box", (0.08, 0.04, 0.02)),
                                      DeclaredGripper("capsule", (0.03, 0.06))])
def test_each_pixels_depth_is_where_its_ray_enters_the_gripper(declared):
    view = _view()
    gripper = GripperShape(declared, _pose([0.02, -0.01, 0.08], (0.3, -0.2, 0.5)))
    depth = gripper.depth(view)
    hit = np.isfinite(depth)
    assert 20 < hit.sum() < depth.size / 2
    rows, cols = np.nonzero(hit)
    # just in front of the hit the ray is outside, just behind it inside
    points = view.world_points(cols, rows, depth[rows, cols])
    rays = view.rays(cols, rows)
    assert not gripper.contains(points - 1e-4 * rays).any()
    assert gripper.contains(points + 1e-4 * rays).all()
    # a ray that misses never enters: sampled along its length
    rows, cols = np.nonzero(~hit)
    pick = np.random.default_rng(0).choice(len(rows), 300, replace=False)
    for z in np.linspace(0.05, 2.0, 80):
        assert not gripper.contains(view.world_points(cols[pick], rows[pick], np.full(300, z))).any()


def test_the_pose_between_two_stamps_is_interpolated_and_held_outside_them():
    poses = [(100, _pose([0.0, 0.0, 0.1])), (200, _pose([0.2, 0.0, 0.1], (0.0, 0.0, np.pi / 2)))]
    middle = gripper_at(poses, 150)
    np.testing.assert_allclose(middle[:3, 3], [0.1, 0.0, 0.1])
    np.testing.assert_allclose(Rotation.from_matrix(middle[:3, :3]).as_euler("xyz")[2], np.pi / 4)
    np.testing.assert_allclose(gripper_at(poses, 50), poses[0][1])
    np.testing.assert_allclose(gripper_at(poses, 250), poses[1][1])
    assert gripper_at([], 150) is None


def test_the_plate_pressing_the_cube_hides_its_top_instead_of_carving_it():
    # the sample bag's gripper plate is background in the masks: as a carving pixel it took the
    # cube's top 2 cm in every frame; at its pose it hides the cube's top and fills its own space
    recording = read_recording(PRESSED)
    truth = read_ground_truth_particles(PRESSED)
    frame_set = match_frames(recording.cameras, 5_000_000)[0]
    reconstructor = Reconstructor(recording.cameras, ReconstructionConfig(use_depth=True), recording.scene)
    pose = gripper_at(recording.gripper_poses, frame_set.stamp_ns)
    hidden = reconstructor.reconstruct(frame_set, pose).objects[1].occupancy
    carved = reconstructor.reconstruct(frame_set).objects[1].occupancy
    true = truth.positions[0][truth.object_id == 1]
    assert carved[:, 2].max() < 0.045 and hidden[:, 2].max() > 0.05  # the true top: 6 cm
    # The cube's top 2 cm (576 voxels) is hidden by the plate from every camera, and so is the
    # space under the plate's overhang beside it. The top continues what the cameras show of the
    # cube below it and is kept (135 of its voxels were, when only what a view shows was kept);
    # the overhang's space does not (830 voxels in this slab when all hidden space was kept).
    assert 0.9 * 576 <= np.sum((hidden[:, 2] > 0.04) & (hidden[:, 2] < 0.06)) <= 1.1 * 576
    assert chamfer_distance(hidden, true) < 0.5 * chamfer_distance(carved, true)
    plate = GripperShape(recording.scene.gripper, pose)
    assert not plate.contains(hidden).any()


def test_space_the_gripper_hides_from_every_camera_is_kept_only_where_the_object_continues_it():
    # The plate lowered beside the cube, 2.5 cm over the floor: the cameras see nothing under it,
    # and no object continues there. With all hidden space kept, 5 voxels were kept there, up to
    # 16 cm from the cube's axis.
    recording = read_recording(PRESSED)
    frame_set = match_frames(recording.cameras, 5_000_000)[0]
    reconstructor = Reconstructor(recording.cameras, ReconstructionConfig(use_depth=True), recording.scene)
    beside = _pose([0.0, 0.13, 0.025])
    occupancy = reconstructor.reconstruct(frame_set, beside).objects[1].occupancy
    assert len(occupancy) > 500
    assert np.linalg.norm(occupancy[:, :2], axis=1).max() < 0.05  # the cube's half-diagonal: 4.2 cm


def test_the_frames_masks_mark_the_plates_background_pixels_occluded():
    recording = read_recording(PRESSED)
    frame_set = match_frames(recording.cameras, 5_000_000)[0]
    config = ReconstructionConfig(use_depth=True)
    reconstructor = Reconstructor(recording.cameras, config, recording.scene)
    pose = gripper_at(recording.gripper_poses, frame_set.stamp_ns)
    observed = reconstructor.reconstruct(frame_set, pose)
    plate = GripperShape(recording.scene.gripper, pose)
    for name, mask in observed.masks.items():
        view = View(recording.cameras[name], frame_set.frames[name], mask_filter=config.mask_filter, use_depth=False)
        covered = np.isfinite(plate.depth(view))
        recorded = view.labels  # filtered as carving reads them
        assert covered.any() and np.all(mask[covered & (recorded == 0)] == OCCLUDED)
        assert np.array_equal(mask[~covered], recorded[~covered])
        assert np.array_equal(mask[recorded == 1], recorded[recorded == 1])  # the cube's own pixels stay
    assert reconstructor.reconstruct(frame_set).masks.keys() == observed.masks.keys()
    assert not any((m == OCCLUDED).any() for m in reconstructor.reconstruct(frame_set).masks.values())


@pytest.mark.parametrize("declared", [DeclaredGripper("box", (0.02, 0.03, 0.01)),
                                      DeclaredGripper("sphere", (0.02,)),
                                      DeclaredGripper("capsule", (0.01, 0.03))])
def test_away_points_from_the_grippers_nearest_point(declared):
    pose = _pose([0.1, -0.2, 0.3], (0.3, -0.5, 1.1))
    shape = GripperShape(declared, pose)
    # the gripper as the points of a 1 mm grid inside it, by brute force
    axis = np.arange(-0.04, 0.0405, 0.001)
    grid = pose[:3, 3] + np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    solid = grid[shape.contains(grid)]
    rng = np.random.default_rng(3)
    points = pose[:3, 3] + rng.normal(size=(300, 3)) * 0.06
    _, nearest = cKDTree(solid).query(points)
    gap = points - solid[nearest]
    far = np.linalg.norm(gap, axis=1) > 0.02  # the grid's 1 mm is a small angle from there
    expected = gap[far] / np.linalg.norm(gap[far], axis=1, keepdims=True)
    away = shape.away(points[far])
    assert far.sum() > 100
    np.testing.assert_allclose(np.linalg.norm(away, axis=1), 1.0)
    angle = np.degrees(np.arccos(np.clip(np.sum(away * expected, axis=1), -1, 1)))
    assert angle.max() < 8.0 and np.median(angle) < 2.0  # the centre's direction: up to 90 on a box
