"""Stages 1-2 on the recorder's sample bag (elastic ball thrown onto plastic clay) against its
ground-truth particles: per-object Chamfer every frame, separation, lifted volumes.

The recorder draws each particle as a ball of ``splat_radius`` (0.8 particle spacings), so what
the cameras see lies about 3 mm outside the solid the particles stand for: a 4 cm ball looks 24%
larger than its particle volume. Volumes are checked against both.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mosiv_ros.config import LiftingConfig, ReconstructionConfig
from mosiv_ros.evaluate.twin import score_frames
from mosiv_ros.io.bag import read_recording
from mosiv_ros.io.recording import match_frames
from mosiv_ros.lifting import lift_first_complete
from mosiv_ros.metrics import chamfer_distance
from mosiv_ros.predict.twin import Prediction
from mosiv_ros.recon import Reconstructor, reconstruct_recording
from mosiv_ros.recon.evaluation import union_of_balls_volume
from mosiv_ros.synth.ground_truth import read_ground_truth, read_ground_truth_particles

BAG = Path(__file__).resolve().parents[1] / "bags" / "elastic_on_plastic"


@pytest.fixture(scope="module")
def sample():
    return read_recording(BAG), read_ground_truth_particles(BAG)


@pytest.fixture(scope="module")
def fused(sample):
    return reconstruct_recording(sample[0], ReconstructionConfig(use_depth=True))


@pytest.mark.parametrize(("use_depth", "limit_mm"), [(True, 5.5), (False, 7.5)])
def test_every_object_of_every_frame_is_within_the_chamfer_limit_and_apart(sample, fused, use_depth,
                                                                           limit_mm):
    recording, truth = sample
    frames = fused if use_depth else reconstruct_recording(recording, ReconstructionConfig(use_depth=False))
    assert len(frames) == len(truth.stamps_ns) == 31
    for k, frame in enumerate(frames):
        assert frame.stamp_ns == truth.stamps_ns[k]
        trees = {i: cKDTree(truth.of_object(i)[k]) for i in (1, 2)}
        for object_id, other in ((1, 2), (2, 1)):
            voxels = frame.objects[object_id].occupancy
            cd = chamfer_distance(voxels, truth.of_object(object_id)[k])
            assert cd < limit_mm * 1e-3, (k, object_id, cd)
            # Apart: voxels nearer the other object's particles than their own are rare.
            nearer = trees[other].query(voxels)[0] < trees[object_id].query(voxels)[0]
            assert nearer.mean() < (0.02 if use_depth else 0.08), (k, object_id)


def test_lifted_volumes_are_within_10_percent_of_what_the_cameras_see_and_never_overlap(sample, fused):
    recording, truth = sample
    lifted = lift_first_complete(fused, LiftingConfig(particle_spacing=0.004), recording.scene)
    assert lifted.stamp_ns == truth.stamps_ns[0]
    splat = read_ground_truth(BAG)["render"]["splat_radius"]
    for object_id in (1, 2):
        particles = truth.of_object(object_id)[0].astype(np.float64)
        seen = union_of_balls_volume(particles, splat, floor=0.0)
        true = float(truth.volume[truth.object_id == object_id].sum())
        volume = lifted.object_volume(object_id)
        assert abs(volume / seen - 1) < 0.10, (object_id, volume, seen)
        assert 1.0 < volume / true < 1.35, (object_id, volume, true)
    cells = np.floor(lifted.x / 0.004).astype(np.int64)
    assert np.unique(cells, axis=0).shape[0] == len(cells)
    assert lifted.families == {1: "elastic", 2: "plastic"}
    assert np.all(lifted.x[:, 2] >= 0.0)  # nothing below the declared ground


def test_hull_the_flying_ball_leaves_on_the_clay_in_the_lifted_frame_is_trimmed_by_the_next_frames(sample,
                                                                                                   fused):
    recording, truth = sample
    clay = truth.of_object(2)[0].astype(np.float64)
    farthest = {}
    for frames in (0, 2):
        lifted = lift_first_complete(fused, LiftingConfig(consensus_frames=frames), recording.scene)
        solid = lifted.x[(lifted.object_id == 2) & (lifted.sdf <= 0)]
        farthest[frames] = cKDTree(clay).query(solid)[0].max()
    # In frame 0 the ball hides part of the clay's near side from one camera: 4 cm of phantom hull.
    assert farthest[0] > 0.03
    assert farthest[2] < 0.012  # half a particle spacing plus the splat and a voxel


def test_a_camera_missing_from_the_whole_recording_is_reported_and_still_gives_every_object(sample):
    recording, truth = sample
    two = read_recording(BAG)
    del two.cameras["cam2"]
    frames = reconstruct_recording(two, ReconstructionConfig(use_depth=False))
    for k, frame in enumerate(frames):
        for object_id in (1, 2):  # degraded (a loose two-view hull), still valid
            assert chamfer_distance(frame.objects[object_id].occupancy, truth.of_object(object_id)[k]) < 0.025
    notes = Reconstructor(two.cameras, ReconstructionConfig(), two.scene).notes
    assert any("only 2 camera(s) (cam0, cam1)" in note for note in notes)



def test_the_thrown_balls_outline_is_not_given_to_the_clay_behind_it():
    # In its first eight frames bags/thrown_ball's ball flies 4-11 cm clear of the clay. Pixels on
    # its outline that the mask filter labels clay, with the ball's own depth, once gave its
    # outline voxels to the clay: the two "touched" in four of the eight frames and the loop
    # closure found no free flight.
    bag = BAG.parent / "thrown_ball"
    recording = read_recording(bag)
    reconstructor = Reconstructor(recording.cameras, ReconstructionConfig(use_depth=True), recording.scene)
    ball, clay = (obj.id for obj in recording.scene.objects)
    for frame_set in match_frames(recording.cameras, 5_000_000)[:8]:
        frame = reconstructor.reconstruct(frame_set)
        gap = cKDTree(frame.objects[clay].occupancy).query(frame.objects[ball].occupancy)[0].min()
        assert gap > 0.03, frame_set.stamp_ns


def test_the_cube_an_image_border_cuts_at_the_start_is_lifted_from_the_first_frame_that_shows_it_whole():
    # bags/sand_and_elastic's cube starts with its top beyond the image border of every camera
    # (frames 0 and 1): lifted there it lacked 9 % of what the cameras see of it, its centroid
    # 4.3 mm off. The third frame shows it whole.
    bag = BAG.parent / "sand_and_elastic"
    recording, truth = read_recording(bag), read_ground_truth_particles(bag)
    frames = reconstruct_recording(recording, ReconstructionConfig(use_depth=True))[:6]
    cube = next(obj.id for obj in recording.scene.objects if obj.name == "cube")
    assert [cube in frame.cut for frame in frames] == [True, True, False, False, False, False]
    lifted = lift_first_complete(frames, LiftingConfig(), recording.scene)
    assert lifted.stamp_ns == truth.stamps_ns[2]
    particles = truth.of_object(cube)[2].astype(np.float64)
    seen = union_of_balls_volume(particles, read_ground_truth(bag)["render"]["splat_radius"], floor=0.0)
    assert abs(lifted.object_volume(cube) / seen - 1) < 0.06, (lifted.object_volume(cube), seen)  # measured +4.5 %
    centroid = lifted.x[(lifted.object_id == cube) & (lifted.sdf <= 0)].mean(axis=0)
    assert np.linalg.norm(centroid - particles.mean(axis=0)) < 0.003  # measured 1.6 mm (4.3 at frame 0)
    # a twin that starts there is scored against the truth at its frames' stamps: the true
    # particles as the prediction are 0 mm from the truth in every frame
    ids = sorted(obj.id for obj in recording.scene.objects)
    prediction = Prediction(lifted.stamp_ns, truth.times[2:6] - truth.times[2], truth.positions[2:6],
                            np.searchsorted(ids, truth.object_id), ids, ["sand", "cube"])
    scores = score_frames(prediction, frames[2:], recording, 3, 0.01, truth, render=False)
    assert [max(s.cd_truth.values()) for s in scores] == [0.0] * 4
