"""The benchmark suite generator: every family pairing, both interactions, recordable scenes."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import yaml

from mosiv_ros.cli import main
from mosiv_ros.io.bag import read_recording
from mosiv_ros.io.scene import FAMILIES
from mosiv_ros.synth.ground_truth import read_ground_truth, read_ground_truth_particles
from mosiv_ros.synth.suite import FAMILY_DEFAULTS, SHAPE_SET, suite_scenes


@pytest.mark.slow
def test_tiny_suite_records_every_unordered_family_pairing_as_readable_bags(tmp_path):
    assert main(["make-suite", str(tmp_path / "suite"), "--size", "tiny"]) == 0
    index = yaml.safe_load((tmp_path / "suite" / "suite.yaml").read_text())
    scenes = index["scenes"]
    pairings = {tuple(sorted(s["families"])) for s in scenes}
    assert pairings == set(itertools.combinations_with_replacement(sorted(FAMILIES), 2))
    assert {s["interaction"] for s in scenes} == {"collide", "stack"}
    assert {shape for s in scenes for shape in s["shapes"]} == set(SHAPE_SET)
    for scene in scenes:
        bag = tmp_path / "suite" / scene["bag"]
        recording = read_recording(bag)
        assert [o.family for o in recording.scene.objects] == scene["families"]
        assert len(recording.cameras) == 2
        truth = read_ground_truth(bag)
        assert [o["shape"] for o in truth["objects"]] == scene["shapes"]
        positions = read_ground_truth_particles(bag).positions
        assert np.all(np.isfinite(positions)) and len(positions) == 7


def test_full_suite_covers_every_ordered_pairing_in_both_interactions_and_lays_out(tmp_path):
    assert main(["make-suite", str(tmp_path / "full"), "--size", "full", "--scenes-only"]) == 0
    scenes = yaml.safe_load((tmp_path / "full" / "suite.yaml").read_text())["scenes"]
    cases = {(tuple(s["families"]), s["interaction"]) for s in scenes}
    assert cases == set(itertools.product(itertools.product(FAMILIES, repeat=2), ("collide", "stack")))
    assert len(scenes) == 64 and all("bag" not in s for s in scenes)
    document = yaml.safe_load((tmp_path / "full" / scenes[0]["scene_file"]).read_text())
    assert document["cameras"]["count"] == 6 and document["cameras"]["fps"] == 30.0


def test_suite_material_parameters_are_jittered_per_scene_and_reproducible_by_seed():
    first, again, other = suite_scenes("tiny", seed=1), suite_scenes("tiny", seed=1), suite_scenes("tiny", seed=2)
    assert [doc for _, doc in first] == [doc for _, doc in again]
    assert [doc for _, doc in first] != [doc for _, doc in other]
    youngs = [o["params"]["E"] for _, doc in first for o in doc["objects"] if "E" in o["params"]]
    assert len(set(youngs)) == len(youngs)
    for _, doc in first:
        for obj in doc["objects"]:
            defaults = FAMILY_DEFAULTS[obj["family"]]
            for key in ("E", "bulk_modulus"):
                if key in obj["params"]:
                    assert 0.5 * defaults[key] <= obj["params"][key] <= 2.0 * defaults[key]


def test_unknown_suite_size_is_refused():
    with pytest.raises(ValueError, match="unknown suite size 'huge'"):
        suite_scenes("huge")
