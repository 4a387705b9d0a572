"""Loop closure on recordings made at test time, each with one undeclared effect (or none).

A 6 cm soft cube (E and nu declared, so the fits stay a few seconds long) seen by two 64x48
cameras at 30 fps: thrown through the air for 0.3 s (air drag, wind, a position-dependent force
field the library does not have, or nothing), or set on a floor tilted by 14 degrees whose low
friction is declared (sliding below the declared floor); seen by three cameras, one of them a
frame ahead of its stamps (a sensor effect); or, with E and nu undeclared, thrown down at the
floor through air with drag. The drag recording also goes through ``mosiv close-loop`` and
through the nodes (identify_node's ``close_loop``). Tolerances and the figures measured are
stated in each test.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import subprocess
import sys

import numpy as np
import pytest
from synth_scenes import record_scene

from mosiv_ros.config import IdentifyConfig, LiftingConfig, from_mapping, updated
from mosiv_ros.identify.problem import views_of
from mosiv_ros.loop.closure import EXPLAINED, NOTHING, UNEXPLAINED, LoopClosure, LoopConfig, Ranked, Round, spread_limit
from mosiv_ros.loop.freeflight import field_law
from mosiv_ros.loop.library import Context, FieldCandidate, FloorTiltCandidate
from mosiv_ros.loop.observations import Observations, Reobserver
from mosiv_ros.prepare import RunConfig, prepare
from mosiv_ros.sim.effects import FIELD_FEATURES

THROW = {
    "name": "throw", "duration": 0.3,
    "objects": [{"name": "jelly", "shape": "box", "size": [0.06, 0.06, 0.06],
                 "position": [-0.1, 0.0, 0.15], "velocity": [0.6, 0.0, 1.2], "family": "elastic",
                 "params": {"E": 1.0e5, "nu": 0.3}, "declared_params": ["E", "nu"],
                 "color": [210, 40, 35]}],
    "cameras": {"placement": "ring", "count": 2, "radius": 0.6, "height": 0.35,
                "look_at": [0.0, 0.0, 0.15], "resolution": [64, 48], "horizontal_fov": 0.9,
                "fps": 30.0},
    "simulation": {"dx": 0.03, "margin": 0.1},
}
FIT = from_mapping(IdentifyConfig, {"curriculum": {"horizons": [0], "iterations": 6},
                                    "search": {"samples": 12, "rounds": 1}, "uncertainty": False,
                                    "loss.silhouette_weight": 0.0, "device": "cpu"})
LIFTING = LiftingConfig(particle_spacing=0.015)


def _scene(effects: list[dict], **object_changes) -> dict:
    scene = copy.deepcopy(THROW)
    scene["effects"] = effects
    scene["objects"][0].update(object_changes)
    return scene


def _close(tmp_path_factory, name: str, scene: dict, fit: IdentifyConfig = FIT,
           loop: LoopConfig = LoopConfig(silhouettes=False)):
    bag = record_scene(tmp_path_factory.mktemp("loop"), scene, name)
    config = RunConfig(lifting=LIFTING)
    prepared = prepare(bag, config)
    closure = LoopClosure(prepared.frames, prepared.lifted, prepared.recording.scene, fit,
                          loop, views_of(prepared.recording),
                          reobserver=Reobserver(prepared.recording, config))
    return closure.run()


def _factor(result) -> float:
    return result.before.held_out_error / result.after.held_out_error


DRAG = {"type": "drag", "coefficient": 5.0, "declared": False}


@pytest.fixture(scope="module")
def drag(tmp_path_factory):
    return _close(tmp_path_factory, "drag", _scene([DRAG]))


@pytest.mark.slow
def test_undeclared_air_drag_is_named_fitted_and_cuts_the_held_out_error(drag):
    assert drag.verdict == EXPLAINED and drag.after.names == ["drag"]
    # in 0.3 s of flight quadratic and linear drag explain the residual alike (measured 0.81 and
    # 0.82); the held-out frames tell them apart (measured x0.16 and x0.31)
    leading = {r.candidate.name: r for r in drag.rounds[0].ranking[:2]}
    assert set(leading) == {"drag", "linear_drag"}
    assert leading["drag"].refit.held_out_error < leading["linear_drag"].refit.held_out_error
    coefficient = drag.after.effects[0][1]["drag.coefficient[jelly]"]
    assert coefficient == pytest.approx(5.0, rel=0.3)  # measured 3.59 (-28 %), refit from 2.09
    assert _factor(drag) >= 2.0


@pytest.mark.slow
def test_with_the_undeclared_drag_accepted_the_stiffness_moves_closer_to_the_truth(tmp_path_factory):
    # E and nu undeclared (truth 30 kPa, 0.3): a softer cube thrown down at the floor, so that
    # the bounce shows its stiffness; without the drag the fit bends E to explain the slowing
    truth = 3.0e4
    scene = _scene([DRAG], params={"E": truth, "nu": 0.3}, declared_params=[],
                   position=[-0.15, 0.0, 0.12], velocity=[1.2, 0.0, -0.6])
    scene["duration"] = 0.4
    # with E free, damping ranks first (a soft, damped cube slows down too): refit three
    result = _close(tmp_path_factory, "stiffness", scene, loop=LoopConfig(silhouettes=False, top_k=3))
    assert result.verdict == EXPLAINED and result.after.names == ["drag"]
    # measured 6.82 with the surface track loss, 5.91 without (loss.track_weight 0): the tracks
    # pull E closer (below) and leave more of the slowing to the drag
    assert result.after.effects[0][1]["drag.coefficient[jelly]"] == pytest.approx(5.0, rel=0.4)
    assert _factor(result) >= 2.0  # measured 8.0x (13.0x without the track loss)
    error = {label: abs(math.log10(model.estimates.objects[0].params["E"] / truth))
             for label, model in (("before", result.before), ("after", result.after))}
    # measured E 4.49 kPa -> 19.1 kPa: |log10 error| 0.82 -> 0.20 (without the track loss 4.50 ->
    # 14.4 kPa: 0.82 -> 0.32)
    assert error["after"] < 0.5 * error["before"] and error["after"] < 0.5


@pytest.mark.slow
def test_undeclared_wind_is_named_fitted_and_cuts_the_held_out_error(tmp_path_factory):
    wind = _close(tmp_path_factory, "wind", _scene([{"type": "wind", "a": [0.0, 3.0, 0.0], "declared": False}]))
    assert wind.verdict == EXPLAINED and wind.after.names == ["wind"]
    values = wind.after.effects[0][1]
    assert values["wind.a[1]"] == pytest.approx(3.0, abs=0.3)
    # measured 0.31 (0.12 while lifting placed surfaces only to within a particle spacing; why the
    # voxel-resolution surfaces move it along the throw is not known)
    assert abs(values["wind.a[0]"]) < 0.4
    assert _factor(wind) >= 2.0


@pytest.mark.slow
def test_undeclared_tilted_floor_is_named_fitted_and_cuts_the_held_out_error(tmp_path_factory):
    # the cube slides from 2 to 5 cm below the declared (flat) floor, which cuts its bottom off the
    # observations: the refit continues on observations remade with its tilted floor
    scene = _scene([{"type": "floor_tilt", "normal": [0.25, 0.0, 1.0], "declared": False},
                    {"type": "floor_friction", "friction": 0.1, "declared": True}],
                   position=[0.05, 0.0, 0.0185], velocity=[0.0, 0.0, 0.0])
    scene["duration"] = 0.4
    scene["cameras"]["look_at"] = [0.1, 0.0, 0.0]
    tilt = _close(tmp_path_factory, "tilt", scene, updated(FIT, {"curriculum.iterations": 15}))
    assert tilt.verdict == EXPLAINED and tilt.after.names == ["floor_tilt"]
    values = tilt.after.effects[0][1]  # the normal is (nx, ny, 1) normalised: truth (0.25, 0)
    # measured 0.237 (0.189 when the refit kept the observations the declared floor cut)
    assert values["ground.normal[0]"] == pytest.approx(0.25, abs=0.03)
    assert abs(values["ground.normal[1]"]) < 0.03
    assert _factor(tilt) >= 2.0  # measured 76.0 -> 19.7 mm (3.9x; 2.7x on the cut observations)


@pytest.mark.slow
def test_a_floor_tilt_remakes_the_observations_with_its_floor_as_their_lower_bound(tmp_path_factory):
    # the cube rests where a floor tilted by 14 degrees lies 5 cm below the declared (flat) one
    scene = _scene([{"type": "floor_tilt", "normal": [0.25, 0.0, 1.0], "declared": False},
                    {"type": "floor_friction", "friction": 1.0, "declared": True}],
                   position=[0.2, 0.0, -0.015], velocity=[0.0, 0.0, 0.0])
    scene["duration"] = 0.1
    scene["cameras"].update(count=3, look_at=[0.1, 0.0, 0.0])
    bag = record_scene(tmp_path_factory.mktemp("loop"), scene, "low")
    config = RunConfig(lifting=LIFTING)
    prepared = prepare(bag, config)
    reobserver = Reobserver(prepared.recording, config)
    given = Observations(prepared.frames, prepared.lifted)
    ctx = Context(["jelly"], [False], prepared.recording.scene, 1 / 30, views_of(prepared.recording),
                  given, reobserver)
    tilt = FloorTiltCandidate()
    changes = tilt.reobserve({"ground.normal[0]": 0.2512, "ground.normal[1]": -0.001}, ctx)
    assert changes["ground"].normal == pytest.approx((0.25, 0.0, 1.0))  # rounded to QUANTUM
    assert tilt.reobserve({"ground.normal[0]": 0.002}, ctx) == {}  # rounds to the declared floor
    assert tilt.reobserve({"ground.normal[0]": 0.25}, dataclasses.replace(ctx, reobserver=None)) == {}
    remade = reobserver.observe(ground=changes["ground"])
    assert reobserver.observe(ground=changes["ground"]) is remade  # cached

    def lowest_and_centroid(frame):
        points = frame.objects[1].occupancy
        return points[:, 2].min(), points.mean(axis=0)

    truth_z = -0.25 * 0.2 + 0.03  # the cube's centre, 3 cm over the tilted floor at x = 0.2
    for before, after in zip(given.frames, remade.frames, strict=True):
        low_before, centre_before = lowest_and_centroid(before)
        low_after, centre_after = lowest_and_centroid(after)
        assert low_before >= -1e-9  # the declared floor cut everything below z = 0
        assert low_after < -0.04  # the tilted floor keeps the cube's bottom (near -0.05 + the tilt)
        assert abs(centre_after[2] - truth_z) < 0.01 < abs(centre_before[2] - truth_z)
    assert remade.lifted.x[:, 2].mean() < given.lifted.x[:, 2].mean() - 0.01


@pytest.mark.slow
def test_an_undeclared_camera_time_offset_is_named_fitted_and_cuts_the_held_out_error(tmp_path_factory):
    # three cameras (with two, an offset of one is an offset of the other); cam1 shows the
    # scene one frame (33.3 ms) ahead of its stamps
    frame = 1.0 / THROW["cameras"]["fps"]
    scene = _scene([{"type": "camera_time_offset", "camera": "cam1", "offset": frame, "declared": False}])
    scene["cameras"]["count"] = 3
    result = _close(tmp_path_factory, "offset", scene)
    assert result.verdict == EXPLAINED and result.after.names == ["camera_time_offset"]
    assert result.rounds[0].ranking[0].candidate.name == "camera_time_offset"
    values = result.after.effects[0][1]  # relative to the median camera, fitted on silhouettes
    assert values["camera_time_offset[cam1]"] == pytest.approx(frame, abs=0.2 * frame)  # measured 33.3 ms
    assert abs(values["camera_time_offset[cam0]"]) < 0.2 * frame  # measured -4.9 ms
    assert abs(values["camera_time_offset[cam2]"]) < 0.2 * frame  # the median camera: 0
    assert _factor(result) >= 2.0  # measured 11.4 -> 4.65 mm (2.4x)


@pytest.mark.slow
def test_without_an_undeclared_effect_nothing_is_accepted(tmp_path_factory):
    result = _close(tmp_path_factory, "plain", _scene([]))
    assert result.verdict == NOTHING and result.after.names == []


@pytest.mark.slow
def test_an_effect_outside_the_library_is_reported_as_unexplained(tmp_path_factory):
    field = {"type": "periodic_field", "a": [0.0, 15.0, 0.0], "wavelength": 0.12, "declared": False}
    result = _close(tmp_path_factory, "field", _scene([field]))
    assert result.rounds[0].significance > LoopConfig().significance  # there is a residual
    assert result.verdict == UNEXPLAINED and result.after.names == []
    library = [r for r in result.rounds[0].ranking if r.candidate.name != "force_field"]
    assert all(r.explained < LoopConfig().min_explained for r in library)
    # free flight shows the force; a wind would explain most of it there, but its refit does worse
    # held out, and so does a smooth field fitted in flight (a_y along the height, measured):
    # both are tried, neither is accepted
    assert result.rounds[0].flight_force
    assert [r.candidate.name for r in result.rounds[0].ranking if r.refit is not None] == ["wind", "force_field"]
    assert not any(r.accepted for r in result.rounds[0].ranking)


def test_the_acceptance_threshold_pays_for_each_knob():
    config = LoopConfig()
    assert config.threshold(1) == pytest.approx(0.8 * 0.905, rel=1e-3)
    assert config.threshold(2) < config.threshold(1)
    with pytest.raises(ValueError, match="holdout"):
        LoopConfig(holdout=1.0)


def test_an_effect_free_flight_shows_may_predict_as_far_as_the_material_only_refits_spread():
    # bags/thrown_ball at the full budget (ca45de1): the declared fit 5.24 mm held out, its
    # control 8.23 mm, the drag refit 8.53 mm: within how far two material-only fits land apart
    assert spread_limit([5.24, 8.23]) == pytest.approx(11.22)
    assert spread_limit([8.23, 5.24]) == spread_limit([5.24, 8.23])
    assert spread_limit([6.0, 6.0]) == 6.0  # refits that agree leave no room beyond them


@pytest.fixture(scope="module")
def drag_bag(tmp_path_factory):
    """The drag recording as a bag, for the command and the node."""
    return record_scene(tmp_path_factory.mktemp("loop"), _scene([DRAG]), "drag")


def _params_file(tmp_path, fast_params):
    """The fast node parameters with the test's fit settings for identify_node."""
    import yaml

    params = yaml.safe_load(fast_params.read_text())
    params["identify_node"]["ros__parameters"].update(
        {"curriculum": dataclasses.asdict(FIT.curriculum), "search": dataclasses.asdict(FIT.search),
         "device": FIT.device})
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    return path


@pytest.mark.slow
def test_an_accepted_field_that_is_a_named_law_is_named_with_the_fields_coefficient(drag_bag):
    # the drag recording's law written as a field (a = -5 |v| v on the axes the cube moves
    # along), refitted (no gradient steps, a fast search): the law free flight favours, so the
    # loop names it drag, held at the field's coefficient, and declares drag in the closed
    # scene; a field along the position is no named law
    config = RunConfig(lifting=LIFTING)
    prepared = prepare(drag_bag, config)
    closure = LoopClosure(prepared.frames, prepared.lifted, prepared.recording.scene,
                          updated(FIT, {"curriculum.iterations": 0}), LoopConfig(silhouettes=False),
                          views_of(prepared.recording), reobserver=Reobserver(prepared.recording, config))
    current = closure.fit([], None, "declared", "declared")
    closure.flight = closure.free_flight(current)
    ctx = closure.context(current)
    round_ = Round(closure.significance(current))
    round_.ranking = [closure.rank(c, current, ctx) for c in closure.library if c.applicable(ctx)]
    assert closure.weigh_flight(round_.ranking, current, ctx)
    features = [FIELD_FEATURES.index(name) for name in ("|v| vx", "|v| vz", "x")]

    def accepted_field(terms, coefficients):
        law = field_law(np.zeros(3), terms)
        candidate = FieldCandidate(terms, np.zeros(3), dict(zip(law.labels, coefficients, strict=True)))
        ranked = Ranked(candidate, math.nan, dict(candidate.values), accepted=True)
        ranked.refit = closure.fit([(candidate, candidate.values)], ctx, "field", candidate.name)
        return ranked

    named = closure.name_field(accepted_field([(features[0], 0), (features[1], 2)], [-5.0, -5.0]), round_, ctx)
    assert named is not None and named.names == ["drag"]
    assert named.effects[0][1]["drag.coefficient[jelly]"] == pytest.approx(5.0, rel=0.01)
    assert [e.name for e in named.scene.effects] == ["drag"]
    assert named.scene.effects[0].params["coefficient"]["jelly"] == pytest.approx(5.0, rel=0.01)
    assert closure.name_field(accepted_field([(features[2], 1)], [20.0]), round_, ctx) is None


@pytest.mark.slow
def test_mosiv_close_loop_writes_the_report_and_a_rerun_resumes_every_fit(tmp_path, fast_params, drag_bag):
    # the command end to end on the drag recording, with the test's fit settings
    out = tmp_path / "report"
    command = [sys.executable, "-m", "mosiv_ros", "close-loop", str(drag_bag), "--out", str(out),
               "--params-file", str(_params_file(tmp_path, fast_params)), "--no-render"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "resuming identification" not in result.stderr
    assert "verdict: explained" in result.stdout and "accepted drag" in result.stdout
    report = json.loads((out / "close_loop.json").read_text())
    assert [e["name"] for e in report["accepted"]] == ["drag"]
    assert report["after"]["metrics"]["future"]["cd"] < report["before"]["metrics"]["future"]["cd"]
    assert report["truth_effects"][0]["type"] == "drag"
    # the reconstruction's own centroid error (the recorder's particles as the prediction): the
    # floor under every model's, a voxel's fraction on this recording
    floor = report["reconstruction_floor"]
    assert 0 < floor["held_out"] < 0.003 and floor["held_out"] < report["after"]["centroid_error"]["held_out"]
    assert "the truth (the recorder's particles)" in (out / "close_loop.md").read_text()
    for name in ("close_loop.md", "closed_scene.yaml", "estimates.yaml", "jelly_paths.png",
                 "jelly_residual.png", "ranking.png"):
        assert (out / name).stat().st_size > 100
    assert "drag" in (out / "closed_scene.yaml").read_text()
    # every fit checkpointed in a folder of its own; the same command again resumes each one
    # where it ended (no search, no iteration) and reaches the same report
    fits = sorted(p.name for p in (out / "checkpoints").iterdir())
    assert {"round0-declared", "round1-control", "round1-drag"} <= set(fits)
    again = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stderr.count("resuming identification") == len(fits)
    rerun = json.loads((out / "close_loop.json").read_text())
    assert rerun["accepted"] == report["accepted"]
    assert rerun["after"]["centroid_error"] == report["after"]["centroid_error"]


@pytest.mark.slow
def test_identify_node_with_close_loop_closes_the_loop_on_its_topics(tmp_path, fast_params, drag_bag):
    # the nodes as processes on the replayed drag recording: identify_node fits, then runs the
    # loop on the frames it received (no silhouettes, no recording: sensor effects not tried)
    from mosiv_ros.graph import Graph, NodeSpec

    bag, out = str(drag_bag), tmp_path / "closed"
    specs = [NodeSpec("reconstruction_node", {"scene": bag}), NodeSpec("lifting_node", {"scene": bag}),
             NodeSpec("identify_node", {"scene": bag, "close_loop": True, "close_loop_dir": str(out),
                                        "output_yaml": str(tmp_path / "estimates.yaml")}),
             # half real time: camera topics are best effort, and on a loaded 2-core machine
             # reconstruction_node missed a frame set at 30 fps (the fit then refuses the gap)
             NodeSpec("bag_replay_node", {"bag": bag, "rate": 0.5, "wait_for_subscribers": 1})]
    with Graph(specs, params_file=_params_file(tmp_path, fast_params), sink=None) as graph:
        graph.wait_for_line("identify_node", "loop closure report written to", 600)
        lines = graph.nodes["identify_node"].lines
    assert any("loop closure: explained; effects added: drag" in line for line in lines)
    report = json.loads((out / "close_loop.json").read_text())
    assert [e["name"] for e in report["accepted"]] == ["drag"]
    assert report["accepted"][0]["values"]["drag.coefficient[jelly]"] == pytest.approx(5.0, rel=0.3)
    errors = report["before"]["centroid_error"]["held_out"], report["after"]["centroid_error"]["held_out"]
    assert errors[1] * 2.0 <= errors[0]
    assert "drag" in (out / "closed_scene.yaml").read_text()
