"""Real node processes on a real DDS graph: replay, latching, malformed messages, the graph."""

from __future__ import annotations

import threading
import time
from collections import defaultdict

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from tf2_msgs.msg import TFMessage

from mosiv_ros.graph import Graph, NodeSpec
from mosiv_ros.io.bag import read_recording
from mosiv_ros.io.messages import (
    camera_info_to_msg,
    image_to_msg,
    rclpy_types,
    stamp_to_ns,
    transform_from_msg,
)

SENSOR = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
LATCHED = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


class Listener:
    """An rclpy node of the test process, spinning in a thread, that records what arrives."""

    def __init__(self, name: str) -> None:
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = Node(name, context=self.context)
        self.received: dict[str, list] = defaultdict(list)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def subscribe(self, msg_type, topic: str, qos) -> None:
        self.node.create_subscription(msg_type, topic, self.received[topic].append, qos)

    def wait_for(self, condition, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if condition():
                return True
            time.sleep(0.05)
        return condition()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)
        self.thread.join(timeout=2.0)


@pytest.fixture
def listener():
    node = Listener("test_listener")
    yield node
    node.close()


@pytest.mark.slow
def test_replay_delivers_every_recorded_image_with_its_recorded_stamp(shapes_bag, listener):
    recording = read_recording(shapes_bag)
    expected = {
        f"/{name}/color/image_raw": [f.stamp_ns for f in camera.frames]
        for name, camera in recording.cameras.items()
    }
    for topic in expected:
        listener.subscribe(Image, topic, SENSOR)
    params = {"bag": str(shapes_bag), "rate": 1.0, "wait_for_subscribers": 1, "linger": 0.5}
    with Graph([NodeSpec("bag_replay_node", params)], sink=None) as graph:
        replay = graph.nodes["bag_replay_node"]
        assert replay.process.wait(60) == 0, "\n".join(replay.lines)
    listener.wait_for(
        lambda: all(len(listener.received[t]) == len(s) for t, s in expected.items()), 5.0)
    for topic, stamps in expected.items():
        got = [stamp_to_ns(m.header.stamp) for m in listener.received[topic]]
        assert got == stamps, topic
    first = listener.received[next(iter(expected))][0]
    camera = next(iter(recording.cameras.values()))
    assert (first.height, first.width, first.encoding) == (
        camera.intrinsics.height, camera.intrinsics.width, "rgb8")


@pytest.mark.slow
def test_latched_tf_static_reaches_a_subscriber_that_starts_after_it_was_published(shapes_bag):
    recording = read_recording(shapes_bag)
    params = {"bag": str(shapes_bag), "rate": 0.0, "linger": 30.0, "start_delay": 0.0}
    with Graph([NodeSpec("bag_replay_node", params)], sink=None) as graph:
        graph.nodes["bag_replay_node"].wait_for_line("replayed", timeout=60)
        late = Listener("late_listener")
        try:
            late.subscribe(TFMessage, "/tf_static", LATCHED)
            assert late.wait_for(lambda: late.received["/tf_static"], 10.0)
            transforms = {}
            for msg in late.received["/tf_static"]:
                for transform in msg.transforms:
                    parent, child, matrix = transform_from_msg(transform)
                    transforms[child] = matrix
        finally:
            late.close()
    for name, camera in recording.cameras.items():
        np.testing.assert_allclose(transforms[f"{name}_optical"], camera.T_world_optical,
                                   atol=1e-9)


@pytest.mark.slow
def test_node_logs_a_malformed_message_and_keeps_processing(listener):
    types = rclpy_types()
    publish = {
        kind: listener.node.create_publisher(msg_type, topic, SENSOR)
        for kind, msg_type, topic in (
            ("rgb", Image, "/camX/color/image_raw"),
            ("mask", Image, "/camX/instance_mask"),
            ("info", CameraInfo, "/camX/color/camera_info"),
        )
    }
    from mosiv_ros.io.recording import CameraIntrinsics

    k = np.array([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])
    intrinsics = CameraIntrinsics(width=32, height=24, K=k, D=np.zeros(5))
    rgb = np.full((24, 32, 3), 200, np.uint8)
    mask = np.zeros((24, 32), np.uint8)
    mask[5:10, 5:10] = 1

    params = {"cameras": ["camX"], "use_depth": False}
    with Graph([NodeSpec("reconstruction_node", params)], sink=None) as graph:
        node = graph.nodes["reconstruction_node"]
        node.wait_for_line("subscribed to cameras camX", timeout=60)
        listener.wait_for(lambda: publish["rgb"].get_subscription_count() > 0, 10.0)
        time.sleep(0.5)
        bad = image_to_msg(types, mask, "mono8", 1_000, "camX_optical")
        bad.data = bad.data[:10]  # truncated payload: 10 bytes for a 32x24 image
        publish["mask"].publish(bad)
        node.wait_for_line("dropped malformed message", timeout=10)
        for stamp in (2_000, 3_000):
            publish["info"].publish(camera_info_to_msg(types, intrinsics, stamp, "camX_optical"))
            publish["rgb"].publish(image_to_msg(types, rgb, "rgb8", stamp, "camX_optical"))
            publish["mask"].publish(image_to_msg(types, mask, "mono8", stamp, "camX_optical"))
        line = node.wait_for_line("frame set 2", timeout=10)
        assert "objects 1 (25 px)" in line
        assert node.process.poll() is None
    error = next(x for x in node.lines if "dropped malformed message" in x)
    assert "/camX/instance_mask" in error
