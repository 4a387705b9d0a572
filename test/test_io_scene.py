"""Scene declarations: schema v1 parsing, validation messages, YAML round trip, loading."""

from __future__ import annotations

import pickle

import pytest

from mosiv_ros.cli import main
from mosiv_ros.io.bag import load_scene
from mosiv_ros.io.errors import MAX_SHOWN_CHARS, BagError, SceneError
from mosiv_ros.io.scene import (
    FAMILIES,
    MAX_YAML_NODES,
    SCENE_KEY,
    DeclaredEffect,
    DeclaredGripper,
    DeclaredGround,
    Scene,
    SceneObject,
    parse_scene,
    scene_to_yaml,
)

EXAMPLE = """
objects:
  - {id: 1, name: red_ball, family: elastic}
  - {id: 2, name: clay, family: plastic, params: {E: 2.0e5}}   # optional known/initial params
gripper: {shape: sphere, radius: 0.02}   # optional collider of /gripper/pose
"""


def test_schema_v1_example_parses():
    scene = parse_scene(EXAMPLE)
    assert scene.objects == [
        SceneObject(1, "red_ball", "elastic", {}),
        SceneObject(2, "clay", "plastic", {"E": 2.0e5}),
    ]
    assert scene.gripper == DeclaredGripper("sphere", (0.02,))
    assert scene.extra == {} and scene.ids == [1, 2]


def test_scene_round_trips_through_yaml_exactly():
    scene = Scene(
        objects=[
            SceneObject(7, "sand_pile", "sand", {"friction_angle_deg": 30, "E": 1.234567890123e6}),
            SceneObject(65535, "water", "fluid"),
        ],
        gripper={"shape": "box", "half_extents": [0.01, 0.02, 0.03], "friction": 0.7},
        extra={"notes": "kept for later schema versions"},
    )
    text = scene_to_yaml(scene)
    assert parse_scene(text) == scene
    assert text.startswith("version: 1\n")


def test_exponents_without_dot_or_sign_are_numbers():
    scene = parse_scene("objects: [{id: 1, name: a, family: fluid, params: {viscosity: 1e-3, E: 5E6}}]")
    assert scene.objects[0].params == {"viscosity": 1e-3, "E": 5e6}


def test_empty_declaration_is_an_empty_scene():
    assert parse_scene("") == Scene()
    assert parse_scene("objects: []\n").objects == []


def test_an_object_may_leave_its_family_out_and_round_trips_without_one():
    scene = parse_scene("objects:\n  - {id: 1, name: heap, params: {density: 1600}}\n"
                        "  - {id: 2, name: cube, family: elastic}\n")
    assert scene.objects[0] == SceneObject(1, "heap", None, {"density": 1600})
    text = scene_to_yaml(scene)
    assert "family" not in text.split("- id: 2")[0]  # not written as family: null
    assert parse_scene(text) == scene


def test_unknown_family_names_the_field_and_the_choices():
    text = "objects:\n  - {id: 1, name: a, family: elastic}\n  - {id: 2, name: b, family: jelly}\n"
    with pytest.raises(SceneError) as info:
        parse_scene(text, source="scene.yaml")
    assert str(info.value) == (
        "scene.yaml: objects[1].family: unknown material family 'jelly' "
        "(expected one of elastic, plastic, sand, fluid)"
    )
    assert info.value.field == "objects[1].family" and FAMILIES == (
        "elastic",
        "plastic",
        "sand",
        "fluid",
    )


def test_an_object_named_scene_is_refused_its_name_is_the_scene_wide_status():
    with pytest.raises(SceneError, match=r"objects\[0\]\.name: 'scene' is reserved"):
        parse_scene("objects:\n  - {id: 1, name: scene, family: elastic}\n")


@pytest.mark.parametrize(
    ("text", "field", "problem"),
    [
        (
            "objects: [{id: 1, name: a, family: elastic}, {id: 1, name: b, family: sand}]",
            "objects[1].id",
            "already used by objects[0]",
        ),
        (
            "objects: [{id: 1, name: a, family: elastic}, {id: 2, name: a, family: sand}]",
            "objects[1].name",
            "already used by objects[0]",
        ),
        ("objects: [{id: 0, name: a, family: elastic}]", "objects[0].id", "outside 1..65535"),
        ("objects: [{id: 65536, name: a, family: elastic}]", "objects[0].id", "outside 1..65535"),
        ("objects: [{id: '1', name: a, family: elastic}]", "objects[0].id", "expected an integer"),
        ("objects: [{id: true, name: a, family: elastic}]", "objects[0].id", "expected an integer"),
        ("objects: [{id: 1.0, name: a, family: elastic}]", "objects[0].id", "expected an integer"),
        ("objects: [{id: 1, name: '', family: elastic}]", "objects[0].name", "non-empty string"),
        ("objects: [{name: a, family: sand}]", "objects[0].id", "missing"),
        ("objects: [{id: 1, name: a, family: sand, parms: {}}]", "objects[0].parms", "unknown key"),
        (
            "objects: [{id: 1, name: a, family: sand, params: {E: soft}}]",
            "objects[0].params.E",
            "finite number",
        ),
        (
            "objects: [{id: 1, name: a, family: sand, params: [1]}]",
            "objects[0].params",
            "expected a mapping",
        ),
        ("objects: [7]", "objects[0]", "expected a mapping"),
        ("objects: {id: 1}", "objects", "expected a list"),
        ("gripper: {shape: sphere}", "gripper.radius", "missing"),
        ("gripper: {shape: sphere, radius: -0.01}", "gripper.radius", "must be positive"),
        ("gripper: {shape: capsule, radius: 0.01}", "gripper.half_length", "missing"),
        ("gripper: {radius: 0.01}", "gripper.shape", "missing"),
        ("gripper: {shape: cone, radius: 0.01}", "gripper.shape", "unknown value 'cone'"),
        ("gripper: {shape: sphere, radius: 0.01, size: 2}", "gripper.size", "unknown key"),
        ("gripper: {shape: sphere, radius: 0.01, friction: 6}", "gripper.friction", "outside [0, 5]"),
        ("version: 2", "version", "unsupported schema version 2"),
    ],
)
def test_invalid_declaration_raises_scene_error_naming_the_field(text, field, problem):
    with pytest.raises(SceneError) as info:
        parse_scene(text, source="test")
    assert info.value.field == field
    assert problem in info.value.problem
    assert str(info.value).startswith(f"test: {field}: ")


def alias_bomb(levels: int, use: str) -> str:
    """``use`` with BOMB replaced by a list of a few hundred characters whose aliases expand to
    ``levels`` nested lists, the last one 10 ** levels strings."""
    lists = ["&l0 [" + ", ".join(['"xxxxxxxx"'] * 10) + "]"]
    lists += [f"&l{k} [{', '.join([f'*l{k - 1}'] * 10)}]" for k in range(1, levels)]
    return use.replace("BOMB", "[" + ", ".join(lists) + "]") + "\n"


@pytest.mark.parametrize("use", ["objects: [BOMB]", "objects: [{id: 1, name: a, params: {E: BOMB}}]",
                                 "ground: {normal: BOMB}"])
def test_yaml_whose_aliases_expand_beyond_the_limit_is_refused_with_a_short_message(use):
    text = alias_bomb(6, use)  # a million strings
    assert len(text) < 600
    with pytest.raises(SceneError) as info:
        parse_scene(text, source="bomb.yaml")
    assert str(info.value).startswith("bomb.yaml: invalid YAML: its aliases expand it to more than "
                                      f"{MAX_YAML_NODES} nodes")
    assert len(str(info.value)) < 300


@pytest.mark.parametrize("use", ["objects: [BOMB]", "objects: [{id: 1, name: a, params: {E: BOMB}}]",
                                 "ground: {normal: BOMB}", "objects: [{id: BOMB, name: a}]"])
def test_a_long_value_is_cut_short_in_the_error_message(use):
    text = alias_bomb(4, use)  # ten thousand strings: within the limit, but not a valid value
    with pytest.raises(SceneError) as info:
        parse_scene(text)
    assert "[['xxxxxxxx'" in info.value.problem and "..." in info.value.problem
    assert len(str(info.value)) < 2 * MAX_SHOWN_CHARS


@pytest.mark.parametrize("text", ["- a\n- b\n", "objects: [\n", "just words"])
def test_text_that_is_not_a_yaml_mapping_raises_scene_error(text):
    with pytest.raises(SceneError, match="<string>"):
        parse_scene(text)


@pytest.mark.parametrize(("params", "field", "problem"), [
    ("{density: -1000}", "objects[1].params.density",
     "density of object 'clay' = -1000 kg/m^3 is out of range [1, 20000] kg/m^3 (mass density)"),
    ("{E: -5.0e4}", "objects[1].params.E", "E of object 'clay' = -50000 Pa is out of range [100, 1e+10] Pa"),
    ("{friction_angle_deg: 80}", "objects[1].params.friction_angle_deg",
     "friction_angle of object 'clay' = 1.39626 rad is out of range [0, 1.0472] rad (Drucker-Prager friction "
     "angle) (given as friction_angle_deg = 80)"),
    ("{stiffness: 3}", "objects[1].params.stiffness",
     "object 'clay': unknown parameter 'stiffness' (known: E, nu, density, "),
])
def test_a_declared_parameter_the_simulator_would_refuse_is_refused_when_read(params, field, problem,
                                                                               small_bag, tmp_path, capsys):
    text = f"objects: [{{id: 1, name: ball}}, {{id: 2, name: clay, family: plastic, params: {params}}}]"
    with pytest.raises(SceneError) as info:
        parse_scene(text, source="test")
    assert info.value.field == field
    assert problem in info.value.problem
    from test_io_bag import rewrite

    bag = rewrite(small_bag, tmp_path / "bag", custom_data={SCENE_KEY: text})
    assert main(["info", str(bag)]) == 2
    assert f"scene declaration (custom_data 'mosiv.scene'): <string>: {field}: " in capsys.readouterr().err


def test_object_by_id_finds_declared_objects_and_rejects_others():
    scene = parse_scene(EXAMPLE)
    assert scene.object_by_id(2).name == "clay"
    with pytest.raises(SceneError, match=r"no object with id 5 \(declared ids: \[1, 2\]\)"):
        scene.object_by_id(5)


def test_building_a_scene_in_code_is_validated_too():
    with pytest.raises(SceneError, match="objects\\[0\\].family"):
        Scene(objects=[SceneObject(1, "a", "rubber")])


def test_load_scene_reads_a_file_inline_text_and_a_bag(tmp_path, small_bag, small_recording):
    path = tmp_path / "scene.yaml"
    path.write_text(EXAMPLE)
    assert load_scene(path) == load_scene(str(path)) == parse_scene(EXAMPLE)
    assert load_scene(EXAMPLE) == parse_scene(EXAMPLE)
    assert load_scene(small_bag) == small_recording.scene
    assert load_scene(str(small_bag)).ids == [1, 2, 3]


def test_load_scene_of_a_bag_without_declaration_is_empty(tmp_path):
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9}\n")
    assert load_scene(bag) == Scene()


def test_load_scene_of_a_missing_file_raises_scene_error_naming_it(tmp_path):
    with pytest.raises(SceneError, match="no_such.yaml: cannot read scene file"):
        load_scene(str(tmp_path / "no_such.yaml"))


def test_a_scene_file_that_is_not_utf8_raises_scene_error_naming_it(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_bytes(b"objects:\n  - {id: 1, name: b\xfell}\n")
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert str(info.value) == f"{path}: not UTF-8 text (byte 0xfe at offset 28)"


def test_load_scene_of_a_directory_that_is_no_bag_raises_bag_error(tmp_path):
    with pytest.raises(BagError, match="no metadata.yaml"):
        load_scene(tmp_path)


def test_errors_survive_pickling_for_the_process_runner(tmp_path):
    scene_error = SceneError("objects[0].id", "missing", "x.yaml")
    bag_error = BagError(tmp_path, "/cam0/instance_mask", "bad")
    for error in (scene_error, bag_error):
        copy = pickle.loads(pickle.dumps(error))
        assert type(copy) is type(error) and str(copy) == str(error)
    assert SCENE_KEY == "mosiv.scene"


DECLARED_EFFECTS = """
objects:
  - {id: 1, name: ball, family: elastic}
  - {id: 2, name: clay, family: plastic}
ground: {height: 0.05, normal: [0.1, 0, 1], friction: 0.8}
effects:
  - name: drag
    params: {coefficient: {ball: 0.5, clay: 1e-1}}
  - {name: wind, params: {a: [0.3, 0, 0]}}
  - {name: damping}
"""


def test_declared_ground_and_effects_parse_and_round_trip():
    scene = parse_scene(DECLARED_EFFECTS)
    assert scene.ground == DeclaredGround(0.05, (0.1, 0.0, 1.0), 0.8)
    assert scene.effects == [
        DeclaredEffect("drag", {"coefficient": {"ball": 0.5, "clay": 0.1}}),
        DeclaredEffect("wind", {"a": [0.3, 0, 0]}),
        DeclaredEffect("damping", {}),
    ]
    assert scene.extra == {}
    assert parse_scene(scene_to_yaml(scene)) == scene


def test_a_scene_without_effects_or_ground_dumps_neither_key():
    text = scene_to_yaml(parse_scene(EXAMPLE))
    assert "effects" not in text and "ground" not in text


@pytest.mark.parametrize(
    ("text", "field", "problem"),
    [
        ("effects: {name: drag}", "effects", "expected a list"),
        ("effects: [drag]", "effects[0]", "expected a mapping"),
        ("effects: [{params: {c: 1}}]", "effects[0].name", "missing"),
        ("effects: [{name: ''}]", "effects[0].name", "non-empty string"),
        ("effects: [{name: drag, declared: true}]", "effects[0].declared", "unknown key"),
        ("effects: [{name: drag}, {name: drag}]", "effects[1].name", "already used by effects[0]"),
        ("effects: [{name: wind, params: {a: [1, x, 0]}}]", "effects[0].params.a[1]", "finite number"),
        ("effects: [{name: drag, params: {coefficient: {ball: .nan}}}]",
         "effects[0].params.coefficient.ball", "finite number"),
        ("effects: [{name: drag, params: 3}]", "effects[0].params", "expected a mapping"),
        ("ground: {height: 0, tilt: 3}", "ground.tilt", "unknown key"),
        ("ground: {normal: [0, 0]}", "ground.normal", "expected a list of 3 numbers"),
        ("ground: {normal: [0, 0, 0]}", "ground.normal", "zero vector"),
        ("ground: {friction: -0.1}", "ground.friction", "must be >= 0"),
        ("ground: [0]", "ground", "expected a mapping"),
    ],
)
def test_invalid_effect_or_ground_declaration_names_the_field(text, field, problem):
    with pytest.raises(SceneError) as info:
        parse_scene(text, source="test")
    assert info.value.field == field
    assert problem in info.value.problem
