"""The synthetic recorder's bags: read back intact, ground truth complete, undeclared effects hidden."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from synth_scenes import FPS, PAIR, pair_scene, record_scene, write_scene

from mosiv_ros.cli import main
from mosiv_ros.io.bag import iter_raw_messages, list_topics, read_custom_data, read_recording
from mosiv_ros.io.scene import DeclaredEffect, DeclaredGround, Scene, SceneObject
from mosiv_ros.sim import FAMILY_PARAMS
from mosiv_ros.synth.cameras import look_at, pinhole
from mosiv_ros.synth.effects import EffectSpec, declaration
from mosiv_ros.synth.ground_truth import (
    GROUND_TRUTH_FILE,
    PARTICLES_FILE,
    read_ground_truth,
    read_ground_truth_particles,
)
from mosiv_ros.synth.scene_file import DEFAULT_START_NS, read_scene_file
from mosiv_ros.synth.shapes import make_shapes_recording

CAMERAS = ("cam0", "cam1", "top", "late")
N_FRAMES = 6  # 0.5 s at 10 fps, both ends


@pytest.fixture(scope="module")
def without_drag(tmp_path_factory):
    """PAIR without its undeclared air drag."""
    effects = [e for e in PAIR["effects"] if e["type"] != "drag"]
    return record_scene(tmp_path_factory.mktemp("synth"), pair_scene(effects=effects), "no_drag")


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    """PAIR with undeclared mask noise and sensor noise, recorded through ``mosiv record``."""
    scene = pair_scene(effects=[*PAIR["effects"], {"type": "mask_noise", "boundary": 0.4, "declared": False}],
                       noise={"rgb_std": 4.0, "depth_std": 0.001})
    directory = tmp_path_factory.mktemp("synth")
    assert main(["record", str(write_scene(directory, scene)), str(directory / "noisy"), "--seed", "7"]) == 0
    return directory / "scene.yaml", directory / "noisy"


def test_recorded_bag_reads_back_with_every_topic_and_stamp(synth_pair_bag):
    topics = list_topics(synth_pair_bag)
    expected = {"/tf_static": 1, "/gripper/pose": N_FRAMES}
    for name in CAMERAS:
        for suffix in ("color/image_raw", "color/camera_info", "instance_mask", "depth/image_rect"):
            expected[f"/{name}/{suffix}"] = N_FRAMES
    assert {name: info.message_count for name, info in topics.items()} == expected
    recording = read_recording(synth_pair_bag)
    stamps = [DEFAULT_START_NS + round(k * 1e9 / FPS) for k in range(N_FRAMES)]
    poses = {p["name"]: look_at(p["position"], p["look_at"]) for p in PAIR["cameras"]["poses"]}
    K = pinhole(64, 48, horizontal_fov=0.9).K
    for name in CAMERAS:
        camera = recording.cameras[name]
        assert camera.stamps_ns == stamps
        assert np.allclose(camera.intrinsics.K, K) and not np.any(camera.intrinsics.D)
        assert np.allclose(camera.T_world_optical, poses[name], atol=1e-9)
        for frame in camera.frames:
            assert frame.rgb.shape == (48, 64, 3) and frame.depth.dtype == np.float32
            assert set(np.unique(frame.mask)) == {0, 1, 2}  # both objects in every view
    assert [stamp for stamp, _ in recording.gripper_poses] == stamps
    for k, (_, T) in enumerate(recording.gripper_poses):
        assert T[:3, 3] == pytest.approx([0.15 - 0.07 * k / (N_FRAMES - 1), 0.0, 0.04])


def test_scene_declaration_holds_objects_gripper_floor_and_declared_effects_only(synth_pair_bag):
    assert read_recording(synth_pair_bag).scene == Scene(
        objects=[SceneObject(1, "clay", "plastic", {"density": 1200.0}), SceneObject(2, "ball", "elastic")],
        gripper={"shape": "sphere", "radius": 0.025},
        ground={"height": 0.0, "friction": 0.8},
        effects=[DeclaredEffect("wind", {"a": [0.5, 0.0, 0.0]}),
                 DeclaredEffect("camera_time_offset", {"offset": {"late": 0.1}})],
    )


def test_ground_truth_lists_every_object_parameter_and_every_effect(synth_pair_bag):
    truth = read_ground_truth(synth_pair_bag)
    clay, ball = truth["objects"]
    assert clay["params"] == {"E": 5.0e4, "nu": 0.3, "yield_stress": 2.0e3, "density": 1200.0, "friction": 0.3}
    assert set(ball["params"]) == set(FAMILY_PARAMS["elastic"]) and ball["params"]["E"] == 4.0e4
    assert [(e["type"], e["declared"]) for e in truth["effects"]] == [
        ("wind", True), ("floor_friction", True), ("camera_time_offset", True), ("drag", False)]
    assert truth["effects"][3]["params"] == {"coefficient": {"clay": 1.5, "ball": 1.5}}
    simulation = truth["simulation"]
    assert simulation["effects"]["drag"]["coefficient"] == pytest.approx({"clay": 1.5, "ball": 1.5})
    assert simulation["effects"]["gravity"]["g"] == pytest.approx([0.0, 0.0, -9.81])
    assert simulation["ground"] == {"height": 0.0, "normal": [0.0, 0.0, 1.0], "friction": 0.8}
    assert simulation["substeps_per_frame"] >= 1 and simulation["simulated_frames"] == N_FRAMES  # + 1 for 'late'
    particles = read_ground_truth_particles(synth_pair_bag)
    assert particles.positions.shape == (N_FRAMES, clay["particles"] + ball["particles"], 3)
    assert list(particles.stamps_ns) == read_recording(synth_pair_bag).cameras["cam0"].stamps_ns
    assert particles.of_object(2)[0].mean(axis=0) == pytest.approx([-0.02, 0.0, 0.12], abs=2e-3)
    heights = particles.of_object(2)[:, :, 2].mean(axis=1)
    # the ball fell onto the slab (5 mm: it rests on it, its contact gap under a 3 cm cell)
    assert heights[-1] < heights[0] - 0.004


def test_undeclared_drag_appears_nowhere_in_the_bag_yet_moves_the_objects(synth_pair_bag, without_drag):
    assert read_custom_data(synth_pair_bag) == read_custom_data(without_drag)
    topics = {n: (t.msgtype, t.message_count) for n, t in list_topics(synth_pair_bag).items()}
    assert topics == {n: (t.msgtype, t.message_count) for n, t in list_topics(without_drag).items()}
    sidecars = {GROUND_TRUTH_FILE, PARTICLES_FILE}
    for path in synth_pair_bag.iterdir():
        if path.name not in sidecars:
            assert b"drag" not in path.read_bytes().lower(), path.name
    for message in iter_raw_messages(synth_pair_bag):
        assert b"drag" not in message.data.lower(), message.topic
    # present in the data: the same scene without drag moves differently (in flight: the ball
    # ends at rest on the slab either way)
    with_drag = read_ground_truth_particles(synth_pair_bag).of_object(2).mean(axis=1)
    no_drag = read_ground_truth_particles(without_drag).of_object(2).mean(axis=1)
    assert np.linalg.norm(with_drag - no_drag, axis=1).max() > 1e-3


def test_a_declared_effect_is_declared_under_its_type_and_floor_effects_under_the_ground():
    effects = [EffectSpec("drag", True, {"coefficient": {"ball": 2.0}}),
               EffectSpec("floor_tilt", True, {"normal": [0.0, 0.1, 0.995]}),
               EffectSpec("wind", False, {"a": [1.0, 0.0, 0.0]})]
    ground, declared = declaration(effects, ground_height=0.02)
    assert ground == DeclaredGround(height=0.02, normal=(0.0, 0.1, 0.995))
    assert declared == [DeclaredEffect("drag", {"coefficient": {"ball": 2.0}})]


def test_mask_noise_moves_only_object_boundary_pixels_to_a_neighbours_label(synth_pair_bag, noisy):
    _, bag = noisy
    clean, dirty = read_recording(synth_pair_bag), read_recording(bag)
    assert np.array_equal(read_ground_truth_particles(bag).positions,
                          read_ground_truth_particles(synth_pair_bag).positions)
    changed = boundary = 0
    for name in CAMERAS:
        for a, b in zip(clean.cameras[name].frames, dirty.cameras[name].frames, strict=True):
            padded = np.pad(a.mask, 1, mode="edge")
            neighbours = np.stack([padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]])
            on_boundary = np.any(neighbours != a.mask, axis=0)
            moved = a.mask != b.mask
            assert not np.any(moved & ~on_boundary)
            assert np.all(np.any(neighbours == b.mask, axis=0)[moved])
            changed, boundary = changed + moved.sum(), boundary + on_boundary.sum()
            assert np.std(b.rgb.astype(float) - a.rgb) == pytest.approx(4.0, rel=0.15)
            depth_noise = (b.depth - a.depth)[np.isfinite(a.depth)]
            assert np.std(depth_noise) == pytest.approx(0.001, rel=0.1)
    # a random one of 4 neighbours, drawn with probability 0.4: at most 0.4, at least 0.4 / 4
    assert 0.1 < changed / boundary < 0.4
    assert dirty.scene.effects == clean.scene.effects  # undeclared: no trace in the declaration


def test_the_same_seed_records_the_same_images(noisy, tmp_path):
    scene_file, bag = noisy
    assert main(["record", str(scene_file), str(tmp_path / "again"), "--seed", "7"]) == 0
    first, second = read_recording(bag), read_recording(tmp_path / "again")
    for name in CAMERAS:
        for a, b in zip(first.cameras[name].frames, second.cameras[name].frames, strict=True):
            assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.mask, b.mask)
            assert np.array_equal(a.depth, b.depth, equal_nan=True)


def test_record_command_refuses_to_overwrite_and_names_bad_fields(tmp_path, synth_pair_bag, capsys):
    scene = write_scene(tmp_path, PAIR)
    assert main(["record", str(scene), str(synth_pair_bag)]) == 2
    assert f"output {synth_pair_bag}: already exists" in capsys.readouterr().err
    bad = pair_scene(duration=-1.0)
    assert main(["record", str(write_scene(tmp_path, bad, "bad.yaml")), str(tmp_path / "out")]) == 2
    assert "duration: must be positive, got -1.0" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_record_refuses_a_recording_too_large_to_hold_before_simulating(tmp_path, capsys, caplog):
    # each within its own limit; together 1001 frames x 4 cameras x 16 MP images
    scene = pair_scene(duration=100.0, cameras={**PAIR["cameras"], "resolution": [4096, 4096], "horizontal_fov": 0.3})
    with caplog.at_level(logging.INFO):
        assert main(["record", str(write_scene(tmp_path, scene)), str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "scene.yaml: cameras.resolution: the recording would hold 563 GiB: images 563 GiB (1001 frames x 4 " \
           "cameras x 4096 x 4096 pixels)" in err
    assert "more than 8 GiB" in err
    assert not any("simulating" in r.getMessage() for r in caplog.records)
    assert not (tmp_path / "out").exists()


SAMPLES = ("elastic_on_plastic", "sand_and_elastic", "thrown_ball", "cube_on_slab")
HIDDEN = {"thrown_ball": ["drag"], "cube_on_slab": ["wind"]}


@pytest.mark.parametrize("name", SAMPLES)
def test_committed_sample_bag_matches_its_scene_file_and_hides_undeclared_effects(name):
    root = Path(__file__).parents[1]
    bag, spec = root / "bags" / name, read_scene_file(root / "config" / "scenes" / f"{name}.yaml")
    recording = read_recording(bag)
    assert [(o.name, o.family) for o in recording.scene.objects] == [(o.name, o.family) for o in spec.objects]
    assert sorted(recording.cameras) == sorted(spec.cameras.names)
    assert all(len(c.frames) == spec.n_frames + 1 for c in recording.cameras.values())
    truth = read_ground_truth(bag)
    assert [o["params"] for o in truth["objects"]] == [o.params for o in spec.objects]
    assert read_ground_truth_particles(bag).positions.shape[0] == spec.n_frames + 1
    hidden = [e.type for e in spec.effects if not e.declared]
    assert [e["type"] for e in truth["effects"] if not e["declared"]] == hidden
    custom = read_custom_data(bag)
    for effect in hidden:
        assert effect not in str(custom) and effect not in (bag / "metadata.yaml").read_text()
    assert hidden == HIDDEN.get(name, [])


def test_committed_analytic_sample_bag_is_what_make_sample_bag_writes_with_its_floor_declared():
    # The analytic scene draws its balls on a floor at z = 0; a twin without that floor lets them
    # fall (the bag shipped without it until the twenty-third session, and its fit diverged).
    shipped = read_recording(Path(__file__).parents[1] / "bags" / "shapes_demo")
    written = make_shapes_recording()
    assert shipped.scene == written.scene
    assert shipped.scene.ground is not None and shipped.scene.ground.plane() == (0.0, (0.0, 0.0, 1.0))
    assert shipped.scene.ground.friction is None  # closed-form paths: no friction to declare
    assert sorted(shipped.cameras) == sorted(written.cameras)
    for name, camera in shipped.cameras.items():
        for got, want in zip(camera.frames, written.cameras[name].frames, strict=True):
            assert got.stamp_ns == want.stamp_ns
            assert np.array_equal(got.mask, want.mask) and np.array_equal(got.rgb, want.rgb)


def _raised(scene: dict, dz: float) -> dict:
    for obj in scene["objects"]:
        obj["position"][2] += dz
    return scene


def test_a_tilted_floor_is_simulated_and_rendered_on_the_tilted_plane(tmp_path):
    normal = np.array([0.2, 0.0, 1.0]) / np.hypot(0.2, 1.0)
    scene = _raised(pair_scene(effects=[{"type": "floor_tilt", "normal": [0.2, 0.0, 1.0], "declared": False}],
                               duration=0.3), 0.04)
    del scene["gripper"]
    bag = record_scene(tmp_path, scene, "tilted")
    recording = read_recording(bag)
    assert recording.scene.ground == DeclaredGround(height=0.0)  # undeclared: the plain floor is all it says
    assert read_ground_truth(bag)["simulation"]["ground"]["normal"] == pytest.approx(normal.tolist())
    for name in ("cam0", "cam1", "top"):
        camera = recording.cameras[name]
        k, T = camera.intrinsics, camera.T_world_optical
        v, u = np.mgrid[0:k.height, 0:k.width]
        rays = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1) @ np.linalg.inv(k.K).T @ T[:3, :3].T
        frame = camera.frames[-1]
        floor = (frame.mask.ravel() == 0) & np.isfinite(frame.depth.ravel())
        points = T[:3, 3] + frame.depth.ravel()[floor, None] * rays[floor]
        assert np.all(np.abs(points @ normal) < 2e-5)
    clay = read_ground_truth_particles(bag).of_object(1)
    assert clay[-1, :, 0].mean() > clay[0, :, 0].mean() + 0.005  # down the slope, towards +x


def test_gravity_damping_and_linear_drag_reach_the_simulator_and_only_declared_ones_the_bag(tmp_path):
    effects = [{"type": "gravity", "g": [1.0, 0.0, -9.76], "declared": True},
               {"type": "damping", "viscosity": {"ball": 5.0}, "declared": False},
               {"type": "linear_drag", "coefficient": 0.5, "declared": True}]
    scene = pair_scene(effects=effects, duration=0.2)
    scene["cameras"]["depth"] = False
    bag = record_scene(tmp_path, scene, "effects")
    simulated = read_ground_truth(bag)["simulation"]["effects"]
    assert simulated["gravity"]["g"] == pytest.approx([1.0, 0.0, -9.76])
    assert simulated["damping"]["viscosity"] == pytest.approx({"clay": 0.0, "ball": 5.0})
    assert simulated["linear_drag"]["coefficient"] == pytest.approx({"clay": 0.5, "ball": 0.5})
    recording = read_recording(bag)
    assert [e.name for e in recording.scene.effects] == ["gravity", "linear_drag"]
    assert recording.scene.effects[0].params == {"g": [1.0, 0.0, -9.76]}
    assert all(frame.depth is None for c in recording.cameras.values() for frame in c.frames)
    assert not any("depth" in topic for topic in list_topics(bag))


def test_fitted_views_keep_a_thrown_ball_inside_every_image_in_every_frame(tmp_path):
    scene = {
        "name": "throw", "duration": 0.4,
        "objects": [{"name": "ball", "shape": "sphere", "radius": 0.04, "position": [0.0, 0.0, 0.05],
                     "velocity": [1.0, 0.3, 0.5], "family": "elastic", "params": {"E": 4.0e4}}],
        "cameras": {"placement": "hemisphere", "count": 3, "radius": 0.5, "look_at": [0.0, 0.0, 0.04],
                    "min_elevation": 0.4, "max_elevation": 1.0, "resolution": [48, 36],
                    "horizontal_fov": 0.8, "fps": FPS},
        "simulation": {"dx": 0.03, "margin": 0.1},
    }

    def border_frames(bag):
        cameras = read_recording(bag).cameras
        edges = [np.r_[f.mask[0], f.mask[-1], f.mask[:, 0], f.mask[:, -1]] for c in cameras.values() for f in c.frames]
        return sum(bool(np.any(edge == 1)) for edge in edges), cameras

    fixed, fixed_cameras = border_frames(record_scene(tmp_path, scene, "fixed"))
    fitted_bag = record_scene(tmp_path, {**scene, "cameras": {**scene["cameras"], "fit_motion": True}}, "fitted")
    fitted, fitted_cameras = border_frames(fitted_bag)
    assert fixed > 0 and fitted == 0  # the ball leaves the fixed views, never the fitted ones
    target = np.array([0.0, 0.0, 0.04])
    scales = [np.linalg.norm(fitted_cameras[n].T_world_optical[:3, 3] - target)
              / np.linalg.norm(fixed_cameras[n].T_world_optical[:3, 3] - target) for n in fixed_cameras]
    assert 1.05 < scales[0] < 4.0 and np.allclose(scales, scales[0])
    for n in fixed_cameras:  # moved back along their lines of sight
        assert np.allclose(fitted_cameras[n].T_world_optical[:3, :3], fixed_cameras[n].T_world_optical[:3, :3])
    truth = read_ground_truth_particles(fitted_bag).positions
    assert np.allclose(truth, read_ground_truth_particles(tmp_path / "fixed").positions)  # the same motion
