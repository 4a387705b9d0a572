"""The declared gripper in stage 1: where it hides the objects, the space it fills, its pose at a stamp."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mosiv_ros.config import ReconstructionConfig
from mosiv_ros.io.bag import read_recording
from mosiv_ros.io.recording import Camera, Frame, match_frames
from mosiv_ros.io.scene import DeclaredGripper
from mosiv_ros.metrics import chamfer_distance
from mosiv_ros.recon import Reconstructor
from mosiv_ros.recon.gripper import GripperShape, gripper_at
from mosiv_ros.recon.views import View
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
    assert chamfer_distance(hidden, true) < 0.5 * chamfer_distance(carved, true)
    plate = GripperShape(recording.scene.gripper, pose)
    assert not plate.contains(hidden).any()
