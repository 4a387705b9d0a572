"""Stage 1 under bad input: noisy masks, a dropped camera, an object leaving the view, bad settings."""

from __future__ import annotations

import copy
import logging

import numpy as np
import pytest
from recon_scenes import ball_points, sphere_recording, time_of, touching_pair
from scipy.spatial import cKDTree

from mosiv_ros.config import ReconstructionConfig
from mosiv_ros.evaluate.twin import view_coverage
from mosiv_ros.io.bag import read_recording, write_recording
from mosiv_ros.io.recording import FrameSet
from mosiv_ros.io.scene import Scene
from mosiv_ros.recon import Reconstructor, reconstruct_recording
from mosiv_ros.recon.evaluation import chamfer_figure
from mosiv_ros.synth.effects import EffectSpec, add_mask_noise
from mosiv_ros.synth.shapes import Sphere, shapes_spheres


@pytest.fixture(scope="module")
def sample():
    spheres = shapes_spheres()
    return spheres, sphere_recording(spheres, n_frames=3)


def worst_figures(spheres, frames) -> tuple[float, float]:
    """(largest relative Chamfer, largest fraction of ground-truth points farther than a voxel
    from every reconstructed voxel: the holes) over objects and frames."""
    worst, holes = 0.0, 0.0
    for frame in frames:
        for s in spheres:
            truth = ball_points(s.centre(time_of(frame.stamp_ns)), s.radius, spacing=0.004)
            voxels = frame.objects[s.id].occupancy
            worst = max(worst, chamfer_figure(s.id, frame.stamp_ns, voxels, truth).relative)
            holes = max(holes, float(np.mean(cKDTree(voxels).query(truth)[0] > 0.005)))
    return worst, holes


def test_the_recorders_mask_noise_is_filtered_and_the_objects_stay_within_3_percent(sample):
    spheres, recording = sample
    noisy = copy.deepcopy(recording)
    noise = [EffectSpec("mask_noise", True, {"boundary": 0.3, "speckle": 0.01})]
    rng = np.random.default_rng(1)
    for camera in noisy.cameras.values():
        for frame in camera.frames:
            frame.mask = add_mask_noise(frame.mask, noise, len(spheres), rng)
    worst, holes = worst_figures(spheres, reconstruct_recording(noisy, ReconstructionConfig()))
    _, raw_holes = worst_figures(spheres, reconstruct_recording(noisy, ReconstructionConfig(mask_filter=0)))
    assert worst < 0.03 and holes < 0.04
    # Unfiltered, background speckles and boundary flips carve rays through the objects.
    assert raw_holes > 1.3 * holes


def test_a_camera_that_stops_midway_is_reported_and_the_others_still_reconstruct_every_object(sample):
    spheres, recording = sample
    dropped = copy.deepcopy(recording)
    dropped.cameras["cam3"].frames = dropped.cameras["cam3"].frames[:1]
    frames = reconstruct_recording(dropped, ReconstructionConfig())
    assert len(frames) == 3 and not frames[0].warnings
    for frame in frames[1:]:
        assert any("no frame from camera(s) cam3" in w for w in frame.warnings)
        assert sorted(frame.objects) == [1, 2, 3] and "cam3" not in frame.masks
    assert worst_figures(spheres, frames)[0] < 0.05


def test_an_object_leaving_every_view_is_reported_and_the_others_are_still_published():
    spheres = [
        Sphere(1, "rocket", "elastic", 0.08, (200, 60, 60), start=(0.0, 0.0), bounce_speed=4.0),
        Sphere(2, "stays", "plastic", 0.08, (60, 200, 60), start=(0.3, -0.2)),
    ]
    frames = reconstruct_recording(sphere_recording(spheres, n_frames=4), ReconstructionConfig())
    assert 1 in frames[1].objects and not frames[1].warnings
    assert any("object 1 (rocket) reaches the image border" in w for w in frames[2].warnings)
    assert 1 in frames[2].objects  # degraded (cut at the border), still there
    assert 1 not in frames[3].objects
    assert any("object 1 (rocket) is seen by no camera" in w for w in frames[3].warnings)
    for frame in frames:
        assert 2 in frame.objects
        cloud = frame.to_cloud()
        assert len(cloud.xyz) > 0 and set(np.unique(cloud.object_id).tolist()) == set(frame.objects)
    # what the run's report says of it: the frames the views do not show it whole in
    cut = frames[2].cut[1]
    assert cut and all(f"reaches the image border of {', '.join(cut)};" in w for w in frames[2].warnings
                       if "reaches the image border" in w)
    assert view_coverage(frames, [(1, "rocket"), (2, "stays")]) == {
        "rocket": {"cut": [k for k, f in enumerate(frames) if 1 in f.cut], "missing": [3],
                   "cameras": sorted({c for f in frames for c in f.cut.get(1, ())})}}
    assert 1 not in frames[0].cut and 1 not in frames[1].cut and 2 not in frames[2].cut


def test_a_declared_ground_keeps_the_objects_shadow_out_of_the_floor():
    spheres = touching_pair()
    recording = sphere_recording(spheres, n_cameras=3)
    free = reconstruct_recording(recording, ReconstructionConfig(use_depth=False))[0]
    recording.scene = Scene(objects=recording.scene.objects, ground={"height": 0.0})
    grounded = reconstruct_recording(recording, ReconstructionConfig(use_depth=False))[0]
    for s in spheres:
        assert np.any(free.objects[s.id].occupancy[:, 2] < 0)  # the hull reaches into the floor
        assert np.all(grounded.objects[s.id].occupancy[:, 2] >= 0)


def test_infinite_zero_and_negative_depth_read_from_a_bag_carve_nothing_and_are_reported_once(
        sample, tmp_path, caplog):
    spheres, recording = sample
    bad = copy.deepcopy(recording)
    for camera in bad.cameras.values():
        for frame in camera.frames:
            frame.depth[:, ::2] = np.inf  # every second column: no return, as +inf
            frame.depth[::4] = 0.0
            frame.depth[1::4] = -1.0
    with caplog.at_level(logging.WARNING, logger="mosiv_ros"):
        read = read_recording(write_recording(bad, tmp_path / "bad"))
    warnings = [r.getMessage() for r in caplog.records if "no usable depth" in r.getMessage()]
    assert sorted(w.split("'")[1] for w in warnings) == sorted(bad.cameras)  # once per camera
    assert all("% of its object pixels" in w for w in warnings)
    clean = reconstruct_recording(recording, ReconstructionConfig())
    for frame, reference in zip(reconstruct_recording(read, ReconstructionConfig()), clean, strict=True):
        for s in spheres:  # the masks still carve: the objects keep their volume
            assert len(frame.objects[s.id].occupancy) == pytest.approx(len(reference.objects[s.id].occupancy),
                                                                       rel=0.05)


def test_a_frame_from_an_uncalibrated_camera_is_rejected_naming_the_camera(sample):
    _, recording = sample
    reconstructor = Reconstructor({"cam0": recording.cameras["cam0"]}, ReconstructionConfig())
    frames = {name: camera.frames[0] for name, camera in recording.cameras.items()}
    with pytest.raises(ValueError, match=r"cam1.*no calibration"):
        reconstructor.reconstruct(FrameSet(frames["cam0"].stamp_ns, frames))


@pytest.mark.parametrize("workspace", [[0.0, 0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 0.0, 1.0, -1.0, 1.0]])
def test_a_malformed_workspace_is_rejected_with_its_values(sample, workspace):
    _, recording = sample
    with pytest.raises(ValueError, match="workspace"):
        Reconstructor(recording.cameras, ReconstructionConfig(workspace=workspace))


def test_voxels_far_finer_than_the_pixels_are_reported_once():
    recording = sphere_recording(touching_pair(), n_cameras=2, width=48, height=36)
    notes = Reconstructor(recording.cameras, ReconstructionConfig()).notes
    finer = [note for note in notes if "consider voxel_size" in note]
    assert len(finer) == 2 and "pixel of cam0" in finer[0] and "pixel of cam1" in finer[1]
    coarse = Reconstructor(recording.cameras, ReconstructionConfig(voxel_size=0.02)).notes
    assert not any("voxel_size" in note for note in coarse)
