"""Prediction for planners: the estimates file as a ROS 2 params file, what-if requests, the node."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import time

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Path as PathMsg
from rcl_interfaces.srv import SetParameters
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2
from synth_scenes import gripper_sweep
from test_io_scene import alias_bomb
from test_nodes_process import LATCHED, Listener
from tf2_msgs.msg import TFMessage

from mosiv_ros.graph import Graph, NodeSpec, executable_path
from mosiv_ros.identify.estimates import WARN, Estimates, ObjectEstimate
from mosiv_ros.io.errors import MAX_SHOWN_CHARS
from mosiv_ros.io.messages import pointcloud_to_msg, rclpy_types, stamp_to_ns
from mosiv_ros.io.scene import scene_to_yaml
from mosiv_ros.nodes.common import STREAM_QOS, TF_STATIC_QOS, lifted_from_msg
from mosiv_ros.predict.request import WhatIf
from mosiv_ros.predict.twin import Twin
from mosiv_ros.prepare import RunConfig, prepare


def _estimates(stamp_ns: int) -> Estimates:
    return Estimates([ObjectEstimate(1, "jelly", "elastic", {"E": 2e4, "nu": 0.3, "density": 1000.0},
                                     {"E": 1.5e3, "nu": float("inf")}, 1e-5, WARN, "poorly identified: nu",
                                     velocity=[0.3, 0.0, -0.4, 0.0, 0.0, 0.0])],
                     {"ground.friction": 0.45}, {"ground.friction": float("nan")}, stamp_ns, 6, 0.1)


@pytest.fixture(scope="module")
def prepared(drop_bag):
    return prepare(drop_bag, RunConfig())


def test_estimates_file_round_trips_and_rclpy_reads_it_as_a_params_file(tmp_path):
    estimates = _estimates(1_700_000_000_000_000_000)
    path = estimates.write(tmp_path / "material_estimates.yaml")
    assert Estimates.read(path).to_yaml() == estimates.to_yaml()  # inf and nan survive too
    # what `ros2 run mosiv_ros prediction_node --ros-args --params-file FILE` gives the node
    context = Context()
    rclpy.init(args=["prediction_node", "--ros-args", "--params-file", str(path)], context=context)
    try:
        node = Node("prediction_node", context=context)
        text = node.declare_parameter("estimates", "").value
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    assert Estimates.from_yaml(text).to_yaml() == estimates.to_yaml()
    (tmp_path / "plain.yaml").write_text(estimates.to_yaml())
    with pytest.raises(ValueError, match="plain.yaml: not a mosiv estimates file"):
        Estimates.read(tmp_path / "plain.yaml")
    with pytest.raises(ValueError, match="malformed estimates document"):
        Estimates.from_yaml("format: mosiv.estimates/1\nobjects: [{id: 1}]\n")


def test_what_if_requests_are_parsed_by_object_and_refused_with_the_reason():
    request = WhatIf.parse("{ball: [0.5, 0, 1.2]}", "{sand: {friction_angle_deg: 30}, ball: {E: 5.0e4}}")
    assert request.velocities == {"ball": [0.5, 0.0, 1.2]}
    assert request.params["sand"] == {"friction_angle": pytest.approx(math.radians(30))}
    families = {"ball": "elastic", "sand": "sand"}
    request.check(families)
    identified = np.array([[0.1, 0.2, 0.3, 1.0, 2.0, 3.0], [0.0] * 6])
    assert request.velocity(identified, ["ball", "sand"])[0].tolist() == [0.5, 0.0, 1.2, 1.0, 2.0, 3.0]
    assert not WhatIf.parse("", " ") and "ball v=[0.5, 0.0, 1.2]" in request.describe()
    for velocities, params, message in [
        ("{ball: [1, 2]}", "", "ball: expected \\[vx, vy, vz\\]"),
        ("{ball: [1, .nan, 0]}", "", "expected finite numbers"),
        ("[1, 2, 3]", "", "initial_velocities: expected a mapping by object name"),
        ("{ball: [1, 2", "", "initial_velocities: not valid YAML"),
        ("", "{ball: 5}", "swapped_params: ball: expected a mapping"),
        ("", "{ball: {E: true}}", "swapped_params: ball.E: expected finite numbers"),
    ]:
        with pytest.raises(ValueError, match=message):
            WhatIf.parse(velocities, params)
    for velocities, params, message in [
        ("{cube: [1, 0, 0]}", "", "unknown object 'cube'; objects: ball, sand"),
        ("", "{ball: {yield_stress: 900}}", "ball \\(elastic\\) has no parameter 'yield_stress'"),
        ("", "{ball: {nu: 0.6}}", "nu of object 'ball' \\(elastic\\) = 0.6  is out of range"),
    ]:
        with pytest.raises(ValueError, match=message):
            WhatIf.parse(velocities, params).check(families)


@pytest.mark.parametrize(("levels", "problem"), [(6, "aliases expand it to more than"),
                                                (4, "expected finite numbers, got [[")])
def test_a_what_if_request_that_grows_without_bound_gets_a_short_error(levels, problem):
    for velocities, params in [(alias_bomb(levels, "ball: BOMB"), ""),
                               ("", alias_bomb(levels, "ball: {E: BOMB}"))]:
        with pytest.raises(ValueError) as info:
            WhatIf.parse(velocities, params)
        assert problem in str(info.value) and len(str(info.value)) < 2 * MAX_SHOWN_CHARS


def test_twin_what_if_rolls_from_the_first_observed_frame_with_the_request(prepared):
    estimates = _estimates(prepared.frames[0].stamp_ns)
    twin = Twin(prepared.lifted, estimates, prepared.recording.scene, device="cpu")
    request = WhatIf.parse("{jelly: [1.0, 0.0, -0.4]}", "{jelly: {E: 2.0e3}}")
    what_if = twin.what_if(request, horizon=0.2, frame_rate=10.0)
    assert what_if.times[0] == 0.0 and what_if.times[-1] == pytest.approx(twin.window_seconds + 0.2)
    direct = twin.predict(twin.window_seconds + 0.2, np.array([[1.0, 0.0, -0.4, 0.0, 0.0, 0.0]]),
                          {"jelly": {"E": 2.0e3}})
    np.testing.assert_array_equal(what_if.positions, direct.positions)  # frames 0.1 s apart: all
    assert np.abs(what_if.positions[-1] - twin.predict(0.7).positions[-1]).max() > 0.05
    assert twin.sim.params.get("E")[0, 0] == pytest.approx(2e4, rel=1e-6)  # the request is undone
    with pytest.raises(ValueError, match="unknown object 'ball'"):
        twin.what_if(WhatIf.parse("{ball: [1, 0, 0]}"), 0.2, 10.0)

def _latch_particles(listener: Listener, prepared):
    """Publish the recording's lifted particles on /mosiv/particles (latched): (publisher, message)."""
    publisher = listener.node.create_publisher(PointCloud2, "/mosiv/particles", LATCHED)
    cloud = prepared.lifted.to_cloud()
    message = pointcloud_to_msg(rclpy_types(), cloud.xyz, cloud.object_id, prepared.frames[0].stamp_ns,
                                cloud.frame_id, cloud.fields)
    publisher.publish(message)
    return publisher, message


def _set(listener: Listener, client, name: str, value):
    """What ``ros2 param set`` does: one SetParameters call; its result."""
    request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
    future = client.call_async(request)
    assert listener.wait_for(future.done, 30), f"no reply to setting {name}"
    return future.result().results[0]


@pytest.mark.slow
def test_prediction_node_predicts_from_an_estimates_file_and_answers_what_if_requests(
        drop_bag, prepared, tmp_path):
    estimates = _estimates(prepared.frames[0].stamp_ns)
    path = estimates.write(tmp_path / "material_estimates.yaml")
    listener = Listener("test_planner")
    try:
        _, particles = _latch_particles(listener, prepared)
        listener.subscribe(PathMsg, "/mosiv/predicted_paths/jelly", LATCHED)
        client = listener.node.create_client(SetParameters, "/prediction_node/set_parameters")
        # the estimates file is the node's params file, as `--params-file FILE` gives it
        spec = NodeSpec("prediction_node", {"scene": str(drop_bag), "horizon": 0.3, "device": "cpu"})
        with Graph([spec], params_file=path, sink=None) as graph:
            node = graph.nodes["prediction_node"]
            node.wait_for_line("predicted", 120)
            assert listener.wait_for(lambda: listener.received["/mosiv/predicted_paths/jelly"], 30)
            identified = listener.received["/mosiv/predicted_paths/jelly"][0]
            assert client.wait_for_service(timeout_sec=10)
            # what `ros2 param set /prediction_node ...` does: refused with the reason, or taken
            refused = _set(listener, client, "initial_velocities", "{cube: [1.0, 0.0, 0.0]}")
            assert not refused.successful and "unknown object 'cube'; objects: jelly" in refused.reason
            assert not _set(listener, client, "scene", "").successful  # read at start only
            accepted = _set(listener, client, "initial_velocities", "{jelly: [1.0, 0.0, -0.4]}")
            assert accepted.successful, accepted.reason
            line = node.wait_for_line("what-if", 120)
            assert "jelly v=[1.0, 0.0, -0.4]" in line
            assert listener.wait_for(lambda: len(listener.received["/mosiv/predicted_paths/jelly"]) > 1, 30)
            what_if = listener.received["/mosiv/predicted_paths/jelly"][-1]
            assert node.process.poll() is None
    finally:
        listener.close()
    stamps = [stamp_to_ns(p.header.stamp) for p in identified.poses]
    assert stamps[0] >= estimates.stamp_ns + 5 * 100_000_000 - 1_000  # past the window (6 frames)
    what_if_stamps = [stamp_to_ns(p.header.stamp) for p in what_if.poses]
    assert what_if_stamps[0] == estimates.stamp_ns  # a what-if starts at the first observed frame
    assert what_if_stamps[-1] == stamps[-1]
    # the node published the core's what-if, from the particles it was sent
    twin = Twin(lifted_from_msg(particles), estimates, prepared.recording.scene, device="cpu")
    expected = twin.what_if(WhatIf.parse("{jelly: [1.0, 0.0, -0.4]}"), 0.3, 10.0).centroids()[:, 0]
    got = [[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in what_if.poses]
    np.testing.assert_allclose(got, expected, atol=1e-6)


@pytest.mark.slow
def test_prediction_node_moves_the_declared_gripper_along_gripper_pose_placed_by_tf_static(
        drop_bag, prepared, tmp_path):
    # a declared 3 cm sphere sweeps through the jelly; its poses come in a robot frame that only
    # /tf_static places in the world (sent after the poses), as a robot driver would publish them
    estimates = _estimates(prepared.frames[0].stamp_ns)
    path = estimates.write(tmp_path / "material_estimates.yaml")
    scene, world_poses = gripper_sweep(prepared.recording.scene, prepared.lifted.x.mean(axis=0),
                                       estimates.stamp_ns)
    scene_file = tmp_path / "scene.yaml"
    scene_file.write_text(scene_to_yaml(scene))
    base = np.eye(4)
    base[:3, 3] = [0.5, -0.2, 0.0]  # T_world_base
    listener = Listener("test_gripper_driver")
    try:
        _, particles = _latch_particles(listener, prepared)
        listener.subscribe(PathMsg, "/mosiv/predicted_paths/jelly", LATCHED)
        poses_pub = listener.node.create_publisher(PoseStamped, "/gripper/pose", STREAM_QOS)
        for stamp, T in world_poses:
            msg = PoseStamped()
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
            msg.header.frame_id = "robot_base"
            x, y, z = (np.linalg.inv(base) @ T)[:3, 3]
            msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = float(x), float(y), float(z)
            msg.pose.orientation.w = 1.0
            poses_pub.publish(msg)
        tf_pub = listener.node.create_publisher(TFMessage, "/tf_static", TF_STATIC_QOS)
        transform = TransformStamped()
        transform.header.frame_id, transform.child_frame_id = "world", "robot_base"
        transform.transform.translation.x, transform.transform.translation.y = 0.5, -0.2
        transform.transform.rotation.w = 1.0
        tf_pub.publish(TFMessage(transforms=[transform]))
        spec = NodeSpec("prediction_node", {"scene": str(scene_file), "horizon": 0.3, "device": "cpu"})
        lifted = lifted_from_msg(particles)  # the node's particles, as it receives them
        pushed = Twin(lifted, estimates, scene, device="cpu", gripper_poses=world_poses).future(0.3, 10.0)
        alone = Twin(lifted, estimates, scene, device="cpu").future(0.3, 10.0)
        expected = pushed.centroids()[:, 0]
        assert np.abs(expected - alone.centroids()[:, 0]).max() > 0.05  # the gripper matters here

        def centroids(msg) -> np.ndarray:
            return np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in msg.poses])

        # the first prediction may come before the poses (latched topics arrive in any order):
        # one with them follows once they stop coming
        with Graph([spec], params_file=path, sink=None):
            assert listener.wait_for(lambda: any(
                np.allclose(centroids(m), expected, atol=1e-6)
                for m in listener.received["/mosiv/predicted_paths/jelly"]), 120)
    finally:
        listener.close()


@pytest.mark.slow
def test_prediction_node_refuses_parameters_out_of_range_with_the_reason_and_keeps_predicting(
        drop_bag, prepared, tmp_path):
    path = _estimates(prepared.frames[0].stamp_ns).write(tmp_path / "material_estimates.yaml")
    listener = Listener("test_prober")
    try:
        _latch_particles(listener, prepared)
        client = listener.node.create_client(SetParameters, "/prediction_node/set_parameters")
        lifting = listener.node.create_client(SetParameters, "/lifting_node/set_parameters")
        specs = [NodeSpec("prediction_node", {"scene": str(drop_bag), "horizon": 0.3, "device": "cpu"}),
                 NodeSpec("lifting_node")]
        with Graph(specs, params_file=path, sink=None) as graph:
            node = graph.nodes["prediction_node"]
            node.wait_for_line("predicted", 120)
            assert client.wait_for_service(timeout_sec=10) and lifting.wait_for_service(timeout_sec=10)
            for name, value, reason in [
                ("horizon", 1e9, "horizon out of range"),  # 1 PiB of rollout frames: it killed the node
                ("horizon", -1.0, "horizon out of range"),
                ("horizon", float("nan"), "horizon out of range"),
                ("frame_rate", 0.0, "frame_rate out of range"),
                ("frame_rate", -5.0, "frame_rate out of range"),
                ("initial_velocities", "{jelly: [1.0e9, 0.0, 0.0]}",
                 "initial_velocities: jelly: 1e+09 m/s is above the limit of 100 m/s"),
                ("initial_velocities", "{jelly: [0, 0, 0, 0, 5.0e3, 0]}", "5000 rad/s is above the limit"),
                ("device", "cpu", "device: read at start only"),
            ]:
                result = _set(listener, client, name, value)
                assert not result.successful and reason in result.reason, (name, value, result.reason)
            # a node that reads its parameters at start only says so rather than ignoring a change
            result = _set(listener, lifting, "particle_spacing", 0.02)
            assert not result.successful and result.reason == "particle_spacing: read at start only"
            time.sleep(1.0)  # a refused change is not rolled out: nothing to crash on
            assert node.process.poll() is None and graph.nodes["lifting_node"].process.poll() is None
            assert _set(listener, client, "horizon", 0.4).successful
            node.wait_for_line("(0.50..0.90 s after the first observed frame)", 120)  # horizon 0.4 s
    finally:
        listener.close()


@pytest.mark.slow
def test_a_node_busy_in_a_long_callback_stops_on_sigterm_within_seconds(drop_bag, prepared, tmp_path):
    path = _estimates(prepared.frames[0].stamp_ns).write(tmp_path / "material_estimates.yaml")
    listener = Listener("test_stopper")
    try:
        publisher, _ = _latch_particles(listener, prepared)
        spec = NodeSpec("prediction_node", {"scene": str(drop_bag), "horizon": 60.0, "device": "cpu"})
        with Graph([spec], params_file=path, sink=None) as graph:
            node = graph.nodes["prediction_node"]
            assert listener.wait_for(lambda: publisher.get_subscription_count() > 0, 20)
            time.sleep(3.0)  # the particles are in: the callback rolls a minute of motion out
            assert not any("predicted" in line for line in node.lines)
            began = time.monotonic()
            os.killpg(node.process.pid, signal.SIGTERM)  # it ran on until the rollout ended
            code = node.process.wait(120)
            stopped = time.monotonic() - began
    finally:
        listener.close()
    assert code == 0 and stopped < 5, (code, stopped, node.tail())


@pytest.mark.slow
def test_prediction_node_refuses_unusable_estimates_at_start_with_one_clear_line():
    result = subprocess.run([str(executable_path("prediction_node")), "--ros-args", "-p",
                             "estimates:=nonsense"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    assert "prediction_node: error: not a mosiv estimates document (a str)" in result.stderr
    result = subprocess.run([str(executable_path("prediction_node")), "--ros-args", "-p",
                             "horizon:=1.0e9"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    assert "prediction_node: error: " in result.stderr and "horizon out of range" in result.stderr
