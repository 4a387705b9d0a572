"""Scene files of the synthetic recorder: the examples load, bad files are rejected by field."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml
from synth_scenes import PAIR, write_scene

from mosiv_ros.cli import main
from mosiv_ros.io.errors import SceneError
from mosiv_ros.io.scene import DeclaredGripper, parse_scene
from mosiv_ros.synth.layout import lay_out
from mosiv_ros.synth.scene_file import parse_scene_file, read_scene_file

SCENES = sorted((Path(__file__).parents[1] / "config" / "scenes").glob("*.yaml"))


def load(scene: dict, base_dir: Path | None = None):
    """Parse and lay out ``scene`` (the checks ``mosiv record`` makes before simulating)."""
    return lay_out(parse_scene_file(yaml.safe_dump(scene), source="test.yaml", base_dir=base_dir))


def changed(path: str, value, **more):
    """PAIR with the value at a dotted path (list indices as numbers) replaced; None deletes it.

    ``more`` replaces top-level keys too.
    """
    scene = copy.deepcopy(PAIR)
    *parents, last = [int(p) if p.isdigit() else p for p in path.split(".")]
    node = scene
    for key in parents:
        node = node[key]
    if value is None:
        del node[last]
    else:
        node[last] = value
    scene.update(more)
    return scene


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_example_scene_files_parse_and_lay_out(path):
    layout = lay_out(read_scene_file(path))
    assert len(layout.bodies) >= 1 and len(layout.x) == len(layout.object_index)


def test_sand_friction_angle_is_given_in_degrees_and_kept_in_radians():
    scene = changed("objects.0", {**PAIR["objects"][0], "family": "sand",
                                  "params": {"friction_angle_deg": 35.0}, "declared_params": ["friction_angle_deg"]})
    spec = load(scene).spec
    assert spec.objects[0].params["friction_angle"] == pytest.approx(math.radians(35.0))
    assert spec.objects[0].declared_params == ["friction_angle"]


def test_particles_start_with_the_objects_linear_and_angular_velocity():
    ball = {**PAIR["objects"][1], "velocity": [0.3, 0.0, -0.5], "angular_velocity": [0.0, 0.0, 4.0]}
    body = load(changed("objects.1", ball)).bodies[1]
    r = body.x - ball["position"]
    assert np.allclose(body.v, np.array([0.3, 0.0, -0.5]) + np.cross([0.0, 0.0, 4.0], r))


def test_a_rotated_box_is_filled_along_its_rotated_axes():
    quarter_turn_z = [0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]
    clay = {**PAIR["objects"][0], "size": [0.16, 0.06, 0.05], "orientation": quarter_turn_z}
    extent = np.ptp(load(changed("objects.0", clay)).bodies[0].x, axis=0)
    assert extent[1] > 2 * extent[0]  # the long side now runs along world y


def test_a_watertight_mesh_is_filled_like_the_solid_it_bounds(tmp_path):
    trimesh.creation.icosphere(subdivisions=3, radius=1.0).export(tmp_path / "ball.stl")
    ball = {k: v for k, v in PAIR["objects"][1].items() if k != "radius"}
    ball.update(shape="mesh", file="ball.stl", scale=0.045)
    mesh_body = load(changed("objects.1", ball), base_dir=tmp_path).bodies[1]
    sphere_body = load(PAIR).bodies[1]
    assert len(mesh_body.rest) == pytest.approx(len(sphere_body.rest), rel=0.1)
    inside = mesh_body.contains(np.array([[-0.02, 0.0, 0.12], [-0.02, 0.0, 0.12 + 0.05]]))
    assert inside.tolist() == [True, False]


def _poses(*poses):
    return [{"name": f"c{i}", "position": p, "look_at": t} for i, (p, t) in enumerate(poses)]


NO_EFFECTS = {"effects": []}
BAD = [
    ("objects.1.family", "jelly", "objects[1].family", "unknown value 'jelly' (expected one of elastic"),
    ("objects.1.radius", -0.1, "objects[1].radius", "must be positive, got -0.1"),
    ("objects.0.size", [0.1, 0.1, -0.05], "objects[0].size[2]", "must be positive, got -0.05"),
    ("objects.1.position", [0.0, 0.0, 0.06], "objects[1].position", "overlaps objects[0] ('clay') at t = 0"),
    ("objects.0.position", [0.0, 0.0, 0.0], "objects[0].position", "below the floor"),
    ("objects.1.colour", [1, 2, 3], "objects[1].colour", "unknown key (allowed for a sphere: name, shape, radius"),
    ("objects.1.size", [0.1, 0.1, 0.1], "objects[1].size", "unknown key (allowed for a sphere"),
    ("objects.1.params", {"yield_stress": 1e3}, "objects[1].params.yield_stress",
     "unknown key (allowed for elastic: E, nu, density, friction)"),
    ("objects.1.params", {"E": 10.0}, "objects[1].params.E", "10.0 is outside [100, 1e+10]"),
    ("objects.1.declared_params", ["yield_stress"], "objects[1].declared_params[0]", "not a parameter of elastic"),
    ("objects.1.name", "clay", "objects[1].name", "already used by objects[0]"),
    ("objects.1.color", [300, 0, 0], "objects[1].color", "0..255"),
    ("objects", [], "objects", "at least one object"),
    ("colour", "red", "colour", "unknown key"),
    ("duration", -1.0, "duration", "must be positive, got -1.0"),
    ("cameras.fps", 0, "cameras.fps", "must be positive, got 0"),
    ("cameras.fov", 1.0, "cameras.fov", "unknown key (allowed for explicit placement"),
    ("cameras.poses", _poses(([0.4, 0.0, 0.3], [0.0, 0.0, 0.05]), ([0.4, 0.0, 0.3], [1.0, 0.0, 0.3])),
     "cameras.poses[1]", "camera 'c1' sees none of the objects at t = 0", NO_EFFECTS),
    ("cameras", {"placement": "ring", "count": 3, "radius": 0.5, "height": 0.3, "look_at": [5.0, 5.0, 0.0],
                 "resolution": [32, 24], "fps": 10}, "cameras", "camera 'cam0' sees none of the objects", NO_EFFECTS),
    ("cameras.resolution", [4, 4], "cameras.resolution", "at least 8 x 8"),
    ("cameras", {**{k: v for k, v in PAIR["cameras"].items() if k != "horizontal_fov"}, "fx": 60.0, "cx": 70.0},
     "cameras", "k[2] (cx) = 70.0: the principal point must lie inside the 64x48 image"),
    ("gripper.trajectory.0.position", [0.03, 0.0, 0.03], "gripper.trajectory", "overlaps an object at t = 0"),
    ("gripper.trajectory.1.t", 0.0, "gripper.trajectory[1].t", "keyframe times must increase"),
    ("gripper.shape", "cone", "gripper.shape", "unknown value 'cone'"),
    ("effects.0.type", "magnetism", "effects[0].type", "unknown value 'magnetism'"),
    ("effects.0.declared", None, "effects[0].declared", "missing"),
    ("effects.3.coefficient", {"balloon": 1.0}, "effects[3].coefficient.balloon", "unknown object"),
    ("effects.3.coefficient", -1.0, "effects[3].coefficient", "outside [0, 1000]"),
    ("effects.3.coef", 1.0, "effects[3].coef", "unknown key (allowed for drag: type, declared, coefficient)"),
    ("effects.2.camera", "cam9", "effects[2].camera", "unknown value 'cam9'"),
    ("effects.1", PAIR["effects"][0], "effects[1].type", "'wind' already given by effects[0]"),
    ("simulation.particle_spacing", 0.05, "simulation.particle_spacing", "must not exceed dx"),
    # what would not fit in memory is refused before it is allocated
    ("cameras.resolution", [100000, 100000], "cameras.resolution", "is 1e+10 pixels, more than 16777216 per camera"),
    ("duration", 1e9, "duration", "1e+09 s at cameras.fps 10 is 1e+10 frames, more than 10000"),
    ("simulation.particle_spacing", 1e-6, "simulation.particle_spacing",
     "objects[0] ('clay') would take 8.4e+14 particles at a spacing of 1e-06 m: with the objects before it more "
     "than 4000000"),
    ("objects.1.radius", 5.0, "simulation.particle_spacing",
     "objects[1] ('ball') would take 2.97e+08 particles at a spacing of 0.015 m"),
]


@pytest.mark.parametrize(("path", "value", "field", "problem", "more"), [(*b, {}) if len(b) == 4 else b for b in BAD],
                         ids=[b[2] + ":" + b[3][:20] for b in BAD])
def test_bad_scene_file_is_rejected_naming_the_field(path, value, field, problem, more):
    with pytest.raises(SceneError) as info:
        load(changed(path, value, **more))
    assert info.value.field == field
    assert problem in info.value.problem
    assert str(info.value).startswith(f"test.yaml: {field}: ")


def test_missing_mesh_file_and_unreadable_yaml_are_rejected(tmp_path):
    ball = {**PAIR["objects"][1], "shape": "mesh", "file": "nowhere.stl"}
    del ball["radius"]
    with pytest.raises(SceneError, match=r"objects\[1\].file: no such mesh file"):
        load(changed("objects.1", ball), base_dir=tmp_path)
    with pytest.raises(SceneError, match="expected a mapping"):
        parse_scene_file("- just\n- a list\n")
    with pytest.raises(SceneError, match="cannot read scene file"):
        read_scene_file(tmp_path / "missing.yaml")
    open_mesh = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    open_mesh.update_faces(np.arange(len(open_mesh.faces) - 2))
    open_mesh.export(tmp_path / "open.stl")
    with pytest.raises(SceneError, match=r"objects\[1\].file: mesh must be a non-empty, watertight"):
        load(changed("objects.1", {**ball, "file": "open.stl"}), base_dir=tmp_path)


def test_a_scene_file_that_is_not_utf8_is_rejected_naming_it(tmp_path, capsys):
    path = tmp_path / "scene.yaml"
    path.write_bytes(yaml.safe_dump(PAIR).encode().replace(b"clay", b"cl\xfey"))
    with pytest.raises(SceneError) as info:
        read_scene_file(path)
    assert str(info.value).startswith(f"{path}: not UTF-8 text (byte 0xfe at offset ")
    assert main(["record", str(path), str(tmp_path / "bag")]) == 2
    assert f"mosiv record: error: {path}: not UTF-8 text" in capsys.readouterr().err


def test_scene_file_written_by_hand_round_trips_through_the_parser(tmp_path):
    spec = read_scene_file(write_scene(tmp_path, PAIR))
    assert [o.name for o in spec.objects] == ["clay", "ball"] and [o.id for o in spec.objects] == [1, 2]
    assert spec.n_frames == 5 and spec.cameras.names == ["cam0", "cam1", "top", "late"]
    assert spec.source.endswith("scene.yaml") and spec.name == "test_pair"


@pytest.mark.parametrize("gripper", [
    {"shape": "box", "half_extents": [0.01, 0.0, 0.01]}, {"shape": "cone", "radius": 0.01},
    {"shape": "capsule", "radius": 0.01}, {"shape": "sphere", "radius": 0.01, "friction": -1},
    {"shape": "sphere", "radius": 0.01, "grip": 1}])
def test_a_scene_file_and_a_bag_declaration_refuse_a_gripper_with_the_same_message(gripper):
    with pytest.raises(SceneError) as declared:
        parse_scene(yaml.safe_dump({"gripper": gripper}))
    trajectory = PAIR["gripper"]["trajectory"]
    with pytest.raises(SceneError) as filed:
        parse_scene_file(yaml.safe_dump({**PAIR, "gripper": {**gripper, "trajectory": trajectory}}))
    assert declared.value.field == filed.value.field
    assert declared.value.problem == filed.value.problem.replace(", color, trajectory", "")


def test_a_recorded_gripper_declares_the_shape_and_size_the_scene_file_gives():
    spec = parse_scene_file(yaml.safe_dump({**PAIR, "gripper": {
        "shape": "capsule", "radius": 0.01, "half_length": 0.03, "friction": 0.9,
        "trajectory": PAIR["gripper"]["trajectory"]}}))
    assert spec.gripper.declaration() == DeclaredGripper("capsule", (0.01, 0.03))
    assert spec.gripper.friction == 0.9

