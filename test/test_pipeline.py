"""The pipeline end to end: in-process ``mosiv run``, the five nodes as processes, estimates."""

from __future__ import annotations

import logging
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Path as PathMsg
from sensor_msgs.msg import PointCloud2
from synth_scenes import gripper_sweep
from test_nodes_process import LATCHED, Listener

from mosiv_ros.config import IdentifyConfig, from_mapping
from mosiv_ros.evaluate.twin import PER_DENSITY, SCENE, parameter_errors
from mosiv_ros.graph import REPLAY_LINGER, Graph, NodeSpec
from mosiv_ros.identify.estimates import ERROR, OK, WARN, Estimates, ObjectEstimate
from mosiv_ros.identify.problem import ProblemError, frame_steps
from mosiv_ros.identify.run import identify_objects
from mosiv_ros.io.bag import read_recording
from mosiv_ros.io.files import MANIFEST, OutputDir
from mosiv_ros.io.messages import pointcloud_from_msg, stamp_to_ns
from mosiv_ros.nodes.outputs import statuses_of
from mosiv_ros.pipeline import evaluate
from mosiv_ros.predict.twin import Twin
from mosiv_ros.prepare import RunConfig, prepare
from mosiv_ros.report import _markdown, frame_ranges


@pytest.mark.slow
def test_mosiv_run_writes_estimates_report_and_plots_and_scores_held_out_frames(
        drop_bag, fast_params, tmp_path):
    out = tmp_path / "run"
    result = subprocess.run([sys.executable, "-m", "mosiv_ros", "run", str(drop_bag), "--out",
                             str(out), "--params-file", str(fast_params)],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"report: {out / 'report.md'}" in result.stdout
    estimates = Estimates.read(out / "estimates.yaml")
    assert [o.name for o in estimates.objects] == ["jelly"]
    assert estimates.objects[0].params["E"] > 0 and estimates.frames == 6  # 70 % of 9 frames
    report = yaml.safe_load((out / "report.json").read_text())
    assert report["fitted_frames"] == 6 and report["frames"] == 9
    assert report["metrics"]["observed"]["frames"] == 5 and report["metrics"]["future"]["frames"] == 3
    for key in ("cd", "emd", "cd_truth", "iou", "psnr", "ssim"):
        assert key in report["metrics"]["future"]
    assert "E" in report["parameter_errors"]["jelly"]  # against ground_truth.yaml
    assert (out / "jelly.png").stat().st_size > 1000
    assert "| jelly | elastic | E |" in (out / "report.md").read_text()


@pytest.mark.slow
def test_five_nodes_give_a_late_subscriber_latched_estimates_and_future_predictions(
        drop_bag, fast_params, tmp_path):
    # Real-time replay: camera topics are best effort with a short queue (the sensor-data
    # profile), which a replay as fast as possible would overflow.
    recording = read_recording(drop_bag)
    bag = str(drop_bag)
    estimates_file = tmp_path / "estimates.yaml"
    specs = [NodeSpec("reconstruction_node", {"scene": bag}), NodeSpec("lifting_node", {"scene": bag}),
             NodeSpec("identify_node", {"scene": bag, "window": 6, "output_yaml": str(estimates_file)}),
             NodeSpec("prediction_node", {"scene": bag}),
             NodeSpec("bag_replay_node", {"bag": bag, "rate": 1.0, "wait_for_subscribers": 1,
                                          "wait_timeout": 60.0})]
    with Graph(specs, params_file=fast_params, sink=None) as graph:
        graph.nodes["identify_node"].wait_for_line("identification done", 300)
        graph.nodes["prediction_node"].wait_for_line("predicted", 120)
        late = Listener("late_planner")  # joins after everything was published
        try:
            late.subscribe(DiagnosticArray, "/mosiv/material_estimates", LATCHED)
            late.subscribe(PointCloud2, "/mosiv/predicted_objects", LATCHED)
            late.subscribe(PathMsg, "/mosiv/predicted_paths/jelly", LATCHED)
            topics = ("/mosiv/material_estimates", "/mosiv/predicted_objects",
                      "/mosiv/predicted_paths/jelly")
            assert late.wait_for(lambda: all(late.received[t] for t in topics), 30)
            estimates = Estimates.from_statuses(statuses_of(late.received[topics[0]][0]))
            cloud = pointcloud_from_msg(late.received[topics[1]][0])
            path = late.received[topics[2]][0]
        finally:
            late.close()
    assert [o.name for o in estimates.objects] == ["jelly"] and estimates.objects[0].level in (OK, WARN)
    assert estimates.frames == 6  # the window: 9 significant digits on the topic, all in the file
    assert Estimates.read(estimates_file).objects[0].params == pytest.approx(estimates.objects[0].params, rel=1e-8)
    last_fitted = recording.cameras["cam0"].frames[5].stamp_ns
    assert cloud.stamp_ns >= last_fitted  # the prediction starts where the fit ended
    assert np.all(cloud.fields["t"] >= 0) and cloud.fields["t"].max() > 0.3
    stamps = [stamp_to_ns(p.header.stamp) for p in path.poses]
    assert stamps[0] >= last_fitted and stamps == sorted(stamps)


@pytest.mark.slow
def test_identify_node_fits_with_the_gripper_the_bag_replays_on_gripper_pose(synth_pair_bag, fast_params):
    # /gripper/pose lives only as long as the replay, and a subscriber matches its publisher only
    # after DDS discovery: the replay starts once identify_node is up and keeps serving for
    # REPLAY_LINGER seconds, as in mosiv graph
    bag = str(synth_pair_bag)
    specs = [NodeSpec("reconstruction_node", {"scene": bag}), NodeSpec("lifting_node", {"scene": bag}),
             NodeSpec("identify_node", {"scene": bag, "window": 4, "output_yaml": ""})]
    expected = len(read_recording(synth_pair_bag).gripper_poses)
    with Graph(specs, params_file=fast_params, sink=None) as graph:
        for name in ("reconstruction_node", "identify_node"):
            graph.nodes[name].wait_for_line(f"{name} ready", 120)
        replay = NodeSpec("bag_replay_node", {"bag": bag, "rate": 1.0, "wait_for_subscribers": 1,
                                              "wait_timeout": 60.0, "linger": REPLAY_LINGER})
        with Graph([replay], sink=None):
            line = graph.nodes["identify_node"].wait_for_line("gripper poses in the world", 300)
        graph.nodes["identify_node"].wait_for_line("identification done", 300)
        lines = graph.nodes["identify_node"].lines
    assert f"{expected} gripper poses" in line and expected > 0
    assert not any("declares a gripper but no pose" in text for text in lines)


@pytest.mark.slow
def test_mosiv_graph_runs_the_node_graph_from_an_empty_kernel_cache_and_prints_where_the_report_is(
        drop_bag, fast_params, tmp_path):
    # An empty Warp kernel cache, as on a fresh machine: identify_node's batched search then
    # compiles the simulator while it runs one simulation per core (it crashed there once:
    # threads built the same module at once).
    out = tmp_path / "graph"
    env = {**os.environ, "WARP_CACHE_PATH": str(tmp_path / "empty-kernel-cache")}
    result = subprocess.run(
        [sys.executable, "-m", "mosiv_ros", "graph", str(drop_bag), "--rate", "1", "--timeout", "400",
         "--params-file", str(fast_params), "--out", str(out)],
        capture_output=True, text=True, timeout=600, env=env)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "[identify_node]" in result.stdout and "sim.runtime: kernels ready on" in result.stdout
    assert (tmp_path / "empty-kernel-cache").is_dir()  # the nodes compiled into it
    assert "Warp CUDA error" not in result.stdout + result.stderr  # a machine without a GPU is not an error
    assert "received 9 complete frame sets; identify_node fitted the first 6" in result.stdout
    assert f"report: {out / 'report.md'}" in result.stdout
    assert (out / "estimates.yaml").is_file() and (out / "report.json").is_file()


@pytest.mark.slow
def test_a_run_removes_an_older_runs_outputs_instead_of_mixing_with_them(drop_bag, tmp_path):
    config = RunConfig(render=False)
    prepared = prepare(drop_bag, config)
    out = tmp_path / "out"

    def estimates(name: str) -> Estimates:
        return Estimates([ObjectEstimate(1, name, "elastic", {"E": 2e4, "nu": 0.3})],
                         stamp_ns=prepared.frames[0].stamp_ns, frames=6, frame_dt=0.1)

    evaluate(prepared, estimates("older"), 6, OutputDir(out, "the older run"), config)
    assert (out / "older.png").is_file()
    (out / "notes.txt").write_text("the user's own file")
    evaluate(prepared, estimates("jelly"), 6, OutputDir(out, "the newer run"), config)
    assert sorted(p.name for p in out.iterdir()) == sorted(["jelly.png", MANIFEST, "notes.txt", "report.json",
                                                            "report.md"])
    assert "older" not in (out / "report.md").read_text()
    manifest = yaml.safe_load((out / MANIFEST).read_text())
    assert manifest["run"] == "the newer run"
    assert sorted(manifest["files"]) == ["jelly.png", "report.json", "report.md"]


def test_frames_are_listed_as_ranges_in_the_report():
    assert frame_ranges([7, 0, 1, 2, 5, 8]) == "0-2, 5, 7-8" and frame_ranges([4]) == "4"
    assert frame_ranges([]) == ""


def test_estimates_survive_the_diagnostic_status_round_trip():
    estimates = Estimates(
        [ObjectEstimate(3, "jelly", "elastic", {"E": 2.5e4, "nu": 0.31}, {"E": 1.2e3}, 1e-5, WARN,
                        "poorly identified: nu", [0.3, 0.0, -0.4, 0.0, 0.1, 0.0],
                        {"elastic": 0.0123, "fluid": float("inf")}),  # family chosen, fluid failed
         ObjectEstimate(4, "slab", "plastic", {"yield_stress": 2e3}, loss=2e-5)],
        {"ground.friction": 0.45}, {"ground.friction": 0.05}, 1_700_000_000_000_000_000, 6, 0.1)
    back = Estimates.from_statuses(estimates.statuses())
    assert back.to_dict() == estimates.to_dict()
    assert Estimates.from_dict(yaml.safe_load(estimates.to_yaml())).to_dict() == estimates.to_dict()
    assert "family_scores" not in estimates.to_dict()["objects"][1]  # a declared family: as before
    with pytest.raises(ValueError, match="status 'mosiv/x': malformed"):
        Estimates.from_statuses([("mosiv/x", "1", OK, "", [("E", "1e4")])])  # no family


def test_parameter_errors_also_compare_scale_parameters_per_unit_density():
    # A fit at an assumed 1000 kg/m^3 of a ball that is 400: E 2.5x too high is E/rho exactly right.
    estimates = Estimates([ObjectEstimate(1, "ball", "elastic",
                                          {"E": 1e5, "nu": 0.25, "density": 1000.0, "friction": 0.5})])
    truth = {"objects": [{"name": "ball", "params": {"E": 4e4, "nu": 0.3, "density": 400.0, "friction": 0.4}}]}
    errors = parameter_errors(estimates, truth)["ball"]
    assert errors["E"]["log10_ratio"] == pytest.approx(math.log10(2.5))
    assert errors["E"][PER_DENSITY] == pytest.approx(0.0, abs=1e-12)
    assert errors["nu"]["abs"] == pytest.approx(-0.05) and PER_DENSITY not in errors["nu"]
    assert errors["friction"]["rel"] == pytest.approx(0.25)
    assert errors["density"]["rel"] == pytest.approx(1.5)
    report = {"bag": "b", "frames": 3, "frame_dt": 0.1, "fitted_frames": 2, "particles": 10,
              "estimates": estimates.to_dict(), "parameter_errors": {"ball": errors}, "metrics": {},
              "timing": {"fit_s": 1.0}}
    row = next(line for line in _markdown(report, []).splitlines() if line.startswith("| ball | elastic | E |"))
    assert "log10_ratio +0.398 (per density +0)" in row


def test_parameter_errors_score_the_ground_and_the_effects_the_fit_found():
    estimates = Estimates([ObjectEstimate(1, "ball", "elastic", {"E": 4e4, "drag.coefficient": 1.2})],
                          scene={"ground.friction": 0.6, "wind.a[1]": 2.5, "ground.normal[0]": 0.1})
    truth = {"objects": [{"name": "ball", "params": {"E": 4e4}}],
             "ground": {"height": 0.0, "normal": [0.0, 0.0, 1.0], "friction": 0.5},
             "effects": [{"type": "drag", "declared": False, "params": {"coefficient": {"ball": 1.5}}},
                         {"type": "wind", "declared": False, "params": {"a": [0.0, 3.0, 0.0]}}]}
    errors = parameter_errors(estimates, truth)
    assert errors["ball"]["drag.coefficient"]["rel"] == pytest.approx(-0.2)
    assert errors[SCENE]["ground.friction"] == {"estimate": 0.6, "truth": 0.5, "rel": pytest.approx(0.2)}
    assert errors[SCENE]["wind.a[1]"]["abs"] == pytest.approx(-0.5)
    assert errors[SCENE]["ground.normal[0]"]["abs"] == pytest.approx(0.1)  # a truth of 0: absolute
    report = {"bag": "b", "frames": 3, "frame_dt": 0.1, "fitted_frames": 2, "particles": 10,
              "estimates": estimates.to_dict(), "parameter_errors": errors, "metrics": {},
              "timing": {"fit_s": 1.0}}
    row = next(line for line in _markdown(report, []).splitlines() if "| ground.friction |" in line)
    assert row.startswith("| scene |  | ground.friction | 0.6 |") and "| 0.5 | rel +0.2 |" in row


def test_a_fit_that_cannot_run_is_reported_as_error_estimates_not_raised(drop_bag):
    config = RunConfig()
    prepared = prepare(drop_bag, config)
    frames = [prepared.frames[i] for i in (0, 1, 7, 8)]  # 5 of 9 frames lost: too few remain
    identification = identify_objects(frames, prepared.lifted, prepared.recording.scene,
                                      from_mapping(IdentifyConfig, {"curriculum.iterations": 1, "uncertainty": False}))
    assert identification.result is None
    obj = identification.estimates.objects[0]
    assert obj.level == ERROR and "too few frames remain: 4 of the 9 frames" in obj.message


def test_frames_a_stream_lost_are_gaps_of_whole_frame_times():
    ms = 1_000_000
    assert frame_steps([0, 100 * ms, 200 * ms]) == (pytest.approx(0.1), [0, 1, 2])
    dt, steps = frame_steps([0, 101 * ms, 199 * ms, 402 * ms, 500 * ms, 800 * ms])  # with jitter
    assert dt == pytest.approx(0.1, abs=0.003) and steps == [0, 1, 2, 4, 5, 8]
    for stamps, message in [([0, 100 * ms, 250 * ms], "frames 1 and 2 are 150.0 ms apart, not a whole number"),
                            ([0, 100 * ms, 700 * ms, 800 * ms], "too few frames remain: 4 of the 9 frames"),
                            ([0, 100 * ms, 100 * ms], "two share a stamp"),
                            ([0], "need at least 2 observed frames")]:
        with pytest.raises(ProblemError, match=message):
            frame_steps(stamps)


@pytest.mark.slow
def test_a_frame_set_the_stream_lost_is_a_gap_the_fit_simulates_through(drop_bag, caplog):
    prepared = prepare(drop_bag, RunConfig())
    frames = [prepared.frames[i] for i in (0, 1, 2, 4, 5)]  # frame 3 lost: the fit failed outright
    config = from_mapping(IdentifyConfig, {"curriculum": {"horizons": [0], "iterations": 2},
                                           "search.samples": 0, "uncertainty": False})
    identification = identify_objects(frames, prepared.lifted, prepared.recording.scene, config)
    assert identification.result is not None, identification.estimates.objects[0].message
    assert identification.estimates.objects[0].level != ERROR
    assert identification.estimates.frames == 6  # frames 0 to 5 simulated, frame 3 among them
    assert "1 of the 6 frames from stamp" in caplog.text and "lost frames 3)" in caplog.text
    observations = identification.identifier.problem.observations
    assert [len(points[0]) > 0 for points in observations.points] == [True, True, True, False, True, True]


def test_twin_predicts_new_initial_conditions_and_swapped_materials(drop_bag):
    prepared = prepare(drop_bag, RunConfig())
    estimates = Estimates([ObjectEstimate(1, "jelly", "elastic", {"E": 2e4, "nu": 0.3},
                                          velocity=[0.3, 0.0, -0.4, 0.0, 0.0, 0.0])],
                          stamp_ns=prepared.frames[0].stamp_ns, frames=6, frame_dt=0.1)
    twin = Twin(prepared.lifted, estimates, prepared.recording.scene, device="cpu")
    thrown = twin.predict(0.5).centroids()[:, 0]
    faster = twin.predict(0.5, velocity=np.array([[1.0, 0.0, -0.4, 0.0, 0.0, 0.0]])).centroids()[:, 0]
    assert faster[3, 0] - faster[0, 0] > thrown[3, 0] - thrown[0, 0] + 0.1  # 0.7 m/s more for 0.3 s
    soft = twin.predict(0.5, params={"jelly": {"E": 2e3}}).positions
    assert np.abs(soft[-1] - twin.predict(0.5).positions[-1]).max() > 0.005
    future = twin.future(0.4, frame_rate=5.0)
    assert future.times[0] == pytest.approx(twin.window_seconds) and np.allclose(np.diff(future.times), 0.2)


def test_twin_follows_an_object_past_its_first_domain_instead_of_stopping_at_the_walls(drop_bag, caplog):
    # frictionless floor, 1.2 m/s along x for 0.8 s: 0.96 m, well past the 0.25 m the first
    # domain leaves around the object; its walls must not stop it
    prepared = prepare(drop_bag, RunConfig())
    estimates = Estimates([ObjectEstimate(1, "jelly", "elastic", {"E": 2e4, "nu": 0.3},
                                          velocity=[1.2, 0.0, 0.0, 0.0, 0.0, 0.0])],
                          scene={"ground.friction": 0.0},
                          stamp_ns=prepared.frames[0].stamp_ns, frames=6, frame_dt=0.1)
    twin = Twin(prepared.lifted, estimates, prepared.recording.scene, device="cpu")
    first_width = twin.sim.hi[0] - twin.sim.lo[0]
    with caplog.at_level(logging.INFO, logger="mosiv_ros.predict.twin"):
        x = twin.predict(0.8).centroids()[:, 0, 0]
    assert "widening it to where they went" in caplog.text
    assert twin.sim.hi[0] - twin.sim.lo[0] > first_width + 0.5
    assert x[-1] - x[0] == pytest.approx(0.96, rel=0.05)
    # the wider simulator keeps the identified values
    assert twin.sim.params.get("ground.friction") == pytest.approx(0.0)
    assert twin.sim.params.get("E")[0, 0] == pytest.approx(2e4, rel=1e-6)


def test_twin_moves_the_declared_gripper_along_its_poses_and_it_pushes_the_object(drop_bag, caplog):
    # a 3 cm sphere sweeps along +x through the resting jelly in 0.3 s, then holds still past
    # its last pose; without its poses the twin leaves it out and says so
    prepared = prepare(drop_bag, RunConfig())
    estimates = Estimates([ObjectEstimate(1, "jelly", "elastic", {"E": 2e4, "nu": 0.3})],
                          stamp_ns=prepared.frames[0].stamp_ns, frames=6, frame_dt=0.1)
    centre = prepared.lifted.x.mean(axis=0)
    scene, poses = gripper_sweep(prepared.recording.scene, centre, estimates.stamp_ns)
    pushed = Twin(prepared.lifted, estimates, scene, device="cpu", gripper_poses=poses).predict(0.5)
    with caplog.at_level(logging.WARNING, logger="mosiv_ros.simulation"):
        alone = Twin(prepared.lifted, estimates, scene, device="cpu").predict(0.5)
    assert "declares a gripper but no pose of it was given" in caplog.text
    moved = pushed.centroids()[-1, 0] - alone.centroids()[-1, 0]
    assert moved[0] > 0.05, moved  # pushed along the sweep (measured: 0.11 m)
    # past the last pose the gripper holds still: no particle deeper in it than about half a
    # grid cell (the collider acts at grid nodes; measured: 2.5 cm from its centre, radius 3 cm)
    assert np.linalg.norm(pushed.positions[-1] - (centre + [0.15, 0.0, 0.0]), axis=1).min() > 0.02


def test_twin_predicts_the_solid_not_the_boundary_band(drop_bag):
    # the lifted particles carry a band up to boundary_band outside the surface (volume ~0) for
    # the M-PhyGs volumes; a prediction reports the particles inside the surface at the offset
    prepared = prepare(drop_bag, RunConfig())
    lifted = prepared.lifted
    assert (lifted.sdf > 0).any()
    for offset in (0.0, 0.004):
        estimates = Estimates([ObjectEstimate(1, "jelly", "elastic",
                                              {"E": 2e4, "nu": 0.3, "boundary_offset": offset})],
                              stamp_ns=prepared.frames[0].stamp_ns, frames=6, frame_dt=0.1)
        first = Twin(lifted, estimates, prepared.recording.scene, device="cpu").predict(0.1).positions[0]
        solid = lifted.sdf + offset <= 0  # one object: its offset is the segment's
        assert len(first) == solid.sum()
        assert np.allclose(first, lifted.x[solid], atol=1e-6)
