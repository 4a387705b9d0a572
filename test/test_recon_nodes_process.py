"""reconstruction_node and lifting_node as real processes give the clouds of the in-process core,
and what lifting_node publishes is what its consumers read."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from recon_scenes import sphere_recording, touching_pair
from sensor_msgs.msg import PointCloud2, PointField
from test_nodes_process import Listener

from mosiv_ros.config import LiftingConfig, ReconstructionConfig
from mosiv_ros.graph import Graph, NodeSpec
from mosiv_ros.io.bag import read_recording, write_recording
from mosiv_ros.io.messages import pointcloud_from_msg, pointcloud_to_msg, rclpy_types
from mosiv_ros.lifting import lift, lift_first_complete
from mosiv_ros.nodes.common import STREAM_QOS, lifted_from_msg
from mosiv_ros.recon import COLOUR_FIELD, TrackPoints, reconstruct_recording

STREAM = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
FRAMES = 5
PRESSED_CUBE = Path(__file__).resolve().parents[1] / "bags" / "pressed_cube"
RECON = {"voxel_size": 0.01}
LIFT = {"particle_spacing": 0.008}


@pytest.fixture
def listener():
    node = Listener("recon_listener")
    yield node
    node.close()


@pytest.mark.slow
def test_replaying_a_bag_through_the_nodes_gives_the_in_process_clouds(tmp_path, listener):
    bag = write_recording(sphere_recording(touching_pair(), n_frames=FRAMES, n_cameras=3, width=96, height=72),
                          tmp_path / "touching")
    listener.subscribe(PointCloud2, "/mosiv/observed_objects", STREAM)
    listener.subscribe(PointCloud2, "/mosiv/surface_tracks", STREAM)
    listener.subscribe(PointCloud2, "/mosiv/particles", LATCHED)
    stages = [NodeSpec("reconstruction_node", {"scene": str(bag), **RECON}),
              NodeSpec("lifting_node", {"scene": str(bag), **LIFT})]
    with Graph(stages, sink=None) as graph:
        for name in ("reconstruction_node", "lifting_node"):
            graph.nodes[name].wait_for_line(f"{name} ready", timeout=60)
        assert listener.wait_for(lambda: listener.node.count_publishers("/mosiv/observed_objects") > 0, 10)
        replay_params = {"bag": str(bag), "rate": 1.0, "wait_for_subscribers": 1, "linger": 0.5}
        with Graph([NodeSpec("bag_replay_node", replay_params)], sink=None) as replay:
            assert replay.nodes["bag_replay_node"].process.wait(60) == 0
        received = listener.wait_for(lambda: len(listener.received["/mosiv/observed_objects"]) == FRAMES
                                     and len(listener.received["/mosiv/surface_tracks"]) == FRAMES
                                     and listener.received["/mosiv/particles"], 30)
        lines = graph.nodes["reconstruction_node"].lines + graph.nodes["lifting_node"].lines
    assert received, "\n".join(lines[-30:])
    assert any("published observed objects 5" in line and " ms" in line for line in lines)
    assert any("published particles of stamp" in line for line in lines)

    recording = read_recording(bag)
    frames = reconstruct_recording(recording, ReconstructionConfig(**RECON))
    for msg, frame in zip(listener.received["/mosiv/observed_objects"], frames, strict=True):
        got, want = pointcloud_from_msg(msg), frame.to_cloud()
        assert msg.header.frame_id == "world" and got.stamp_ns == want.stamp_ns
        np.testing.assert_array_equal(got.object_id, want.object_id)
        np.testing.assert_array_equal(got.xyz, want.xyz)
        np.testing.assert_array_equal(got.fields["voxel_size"], want.fields["voxel_size"])
        np.testing.assert_array_equal(got.fields[COLOUR_FIELD], want.fields[COLOUR_FIELD])
    # The surface tracks: the same points, ids and confidences, their field types as the contract says.
    for msg, frame in zip(listener.received["/mosiv/surface_tracks"], frames, strict=True):
        got, want = TrackPoints.from_cloud(pointcloud_from_msg(msg)), frame.tracks
        assert {f.name: f.datatype for f in msg.fields} == {
            "x": PointField.FLOAT32, "y": PointField.FLOAT32, "z": PointField.FLOAT32,
            "object_id": PointField.UINT16, "track_id": PointField.UINT32, "confidence": PointField.FLOAT32}
        assert msg.header.frame_id == "world" and got.stamp_ns == want.stamp_ns
        np.testing.assert_array_equal(got.xyz, want.xyz.astype(np.float32))
        for name in ("object_id", "track_id", "confidence"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name).astype(getattr(got, name).dtype))
    assert sum(len(f.tracks.track_id) for f in frames) > 0
    lifted = lift_first_complete(frames, LiftingConfig(**LIFT), recording.scene)
    got, want = pointcloud_from_msg(listener.received["/mosiv/particles"][-1]), lifted.to_cloud()
    assert got.stamp_ns == want.stamp_ns == frames[0].stamp_ns
    np.testing.assert_array_equal(got.object_id, want.object_id)
    np.testing.assert_array_equal(got.xyz, want.xyz)
    for name, values in want.fields.items():
        np.testing.assert_array_equal(got.fields[name], values, err_msg=name)


def _replayed_through_reconstruction(listener, bag, params: dict, count: int) -> tuple[bool, list[str]]:
    """Replay ``bag`` into a reconstruction_node (``params``) until ``count`` observed clouds came.

    (Whether they came, the node's log lines); the node must still be running at the end.
    """
    listener.subscribe(PointCloud2, "/mosiv/observed_objects", STREAM)
    with Graph([NodeSpec("reconstruction_node", {"scene": str(bag), **params})], sink=None) as graph:
        node = graph.nodes["reconstruction_node"]
        node.wait_for_line("reconstruction_node ready", timeout=60)
        assert listener.wait_for(lambda: listener.node.count_publishers("/mosiv/observed_objects") > 0, 10)
        replay_params = {"bag": str(bag), "rate": 1.0, "wait_for_subscribers": 1, "linger": 0.5}
        with Graph([NodeSpec("bag_replay_node", replay_params)], sink=None) as replay:
            assert replay.nodes["bag_replay_node"].process.wait(60) == 0
        received = listener.wait_for(lambda: len(listener.received["/mosiv/observed_objects"]) == count, 60)
        assert node.process.poll() is None
        return received, list(node.lines)


@pytest.mark.slow
def test_a_camera_that_stops_publishing_degrades_the_nodes_output_but_never_stops_it(tmp_path, listener):
    recording = sphere_recording(touching_pair(), n_frames=FRAMES, n_cameras=3, width=96, height=72)
    recording.cameras["cam2"].frames = recording.cameras["cam2"].frames[:2]
    bag = write_recording(recording, tmp_path / "lossy")
    received, lines = _replayed_through_reconstruction(listener, bag, RECON, FRAMES)
    assert received, "\n".join(lines[-30:])
    assert sum("no frame from camera(s) cam2" in line for line in lines) == FRAMES - 2
    frames = reconstruct_recording(read_recording(bag), ReconstructionConfig(**RECON))
    for msg, frame in zip(listener.received["/mosiv/observed_objects"], frames, strict=True):
        got, want = pointcloud_from_msg(msg), frame.to_cloud()
        assert set(np.unique(got.object_id).tolist()) == {1, 2, 3}
        np.testing.assert_array_equal(got.xyz, want.xyz)



@pytest.mark.slow
def test_a_burst_of_frames_faster_than_the_node_takes_them_reaches_it_whole(tmp_path, listener):
    # the replay as fast as possible: each camera topic gets its 20 messages within milliseconds,
    # more than the sensor-data profile's keep last 5 (which kept 6 of the 20 frame sets); the
    # node's subscriptions hold image_history (30) until it takes them
    n_frames = 20
    recording = sphere_recording(touching_pair(), n_frames=n_frames, n_cameras=2, width=64, height=48)
    bag = write_recording(recording, tmp_path / "burst")
    params = {"scene": str(bag), "cameras": ["cam0", "cam1"], "use_depth": False, **RECON}
    with Graph([NodeSpec("reconstruction_node", params)], sink=None) as graph:
        node = graph.nodes["reconstruction_node"]
        node.wait_for_line("subscribed to cameras", timeout=60)
        replay_params = {"bag": str(bag), "rate": 0.0, "wait_for_subscribers": 1, "linger": 0.5}
        with Graph([NodeSpec("bag_replay_node", replay_params)], sink=None) as replay:
            assert replay.nodes["bag_replay_node"].process.wait(60) == 0
        node.wait_for_line(f"frame set {n_frames}:", timeout=30)
        assert node.process.poll() is None
        sets = [line for line in node.lines if ": frame set " in line]
    assert len(sets) == n_frames and all("cameras cam0, cam1," in line for line in sets), "\n".join(sets)


@pytest.mark.slow
def test_reconstruction_node_lets_the_gripper_on_gripper_pose_hide_the_cube_as_the_core_does(listener):
    # bags/pressed_cube: a plate the masks leave out presses the cube; the node places it from
    # /gripper/pose and /tf_static, and its clouds are the in-process core's, which uses the poses
    # and a set waits for the pose at its stamp however slow the machine (a timeout past any stall)
    frames = reconstruct_recording(read_recording(PRESSED_CUBE), ReconstructionConfig())
    received, lines = _replayed_through_reconstruction(listener, PRESSED_CUBE, {"partial_set_timeout": 30.0},
                                                       len(frames))
    assert received, "\n".join(lines[-30:])
    assert not any("gripper held at its pose" in line for line in lines)
    for msg, frame in zip(listener.received["/mosiv/observed_objects"], frames, strict=True):
        got, want = pointcloud_from_msg(msg), frame.to_cloud()
        np.testing.assert_array_equal(got.xyz, want.xyz)
    assert frames[0].objects[1].occupancy[:, 2].max() > 0.05  # the cube's top, under the plate


@pytest.mark.slow
def test_a_gripper_pose_stream_that_stops_leaves_the_gripper_where_it_last_was_with_one_warning(tmp_path, listener):
    # the poses stop after the 8th of 19 frames: the later sets wait no longer than the streams
    # allow, hold the last pose (as the core does past the last pose) and say so once
    recording = read_recording(PRESSED_CUBE)
    recording.gripper_poses = recording.gripper_poses[:8]
    bag = write_recording(recording, tmp_path / "poses_stop")
    frames = reconstruct_recording(read_recording(bag), ReconstructionConfig())
    received, lines = _replayed_through_reconstruction(listener, bag, {}, len(frames))
    assert received, "\n".join(lines[-30:])
    held = [line for line in lines if "gripper held at its pose" in line]
    assert len(held) == 1 and f"pose of stamp {recording.gripper_poses[-1][0]} ns" in held[0], held
    for msg, frame in zip(listener.received["/mosiv/observed_objects"], frames, strict=True):
        np.testing.assert_array_equal(pointcloud_from_msg(msg).xyz, frame.to_cloud().xyz)


@pytest.mark.slow
def test_lifting_nodes_boundary_settings_reach_identify_node(listener):
    """A boundary_beta and boundary_eps other than the defaults travel on /mosiv/particles."""
    recording = sphere_recording(touching_pair(), n_frames=1, n_cameras=3, width=96, height=72)
    cloud = reconstruct_recording(recording, ReconstructionConfig(**RECON))[0].to_cloud()
    lifting = {**LIFT, "boundary_beta": 800.0, "boundary_eps": 0.01, "consensus_frames": 0}
    observed = listener.node.create_publisher(PointCloud2, "/mosiv/observed_objects", STREAM_QOS)
    listener.subscribe(PointCloud2, "/mosiv/particles", LATCHED)
    # identify_node gets the particles and a single frame: it waits for more and never fits
    stages = [NodeSpec("lifting_node", lifting),
              NodeSpec("identify_node", {"device": "cpu", "window": 10, "output_yaml": ""})]
    with Graph(stages, sink=None) as graph:
        assert listener.wait_for(lambda: observed.get_subscription_count() >= 2, 20)
        observed.publish(pointcloud_to_msg(rclpy_types(), cloud.xyz, cloud.object_id, cloud.stamp_ns,
                                           "world", cloud.fields))
        line = graph.nodes["identify_node"].wait_for_line("/mosiv/particles:", 60)
        assert listener.wait_for(lambda: listener.received["/mosiv/particles"], 10)
    want = lift(cloud, LiftingConfig(**lifting))
    # the particles' volumes as identify_node reads them: those lifting_node lifted
    assert line.split("/mosiv/particles: ")[1].rsplit(" in ", 1)[0] == want.summary().rsplit(" in ", 1)[0]
    seen = lifted_from_msg(listener.received["/mosiv/particles"][-1])
    assert (seen.beta, seen.eps) == (800.0, 0.01)
