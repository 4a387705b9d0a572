"""bag_replay_node: publish a rosbag2 recording's topics with their recorded stamps.

Messages go out exactly as recorded (the stored CDR bytes), paced by the recorded receive times
divided by ``rate``. Camera topics use the sensor-data QoS, ``/tf_static`` is latched
(reliable + transient_local, deep enough to hold every recorded static transform), anything
else is reliable.
"""

from __future__ import annotations

import threading
import time

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future

from mosiv_ros.config import ReplayConfig
from mosiv_ros.io.bag import iter_raw_messages, list_topics
from mosiv_ros.io.messages import rclpy_types
from mosiv_ros.io.replay import paced
from mosiv_ros.nodes.common import SENSOR_QOS, STREAM_QOS, declare_config, main_for

NAME = "bag_replay_node"
SUMMARY = "replay a rosbag2 recording's topics with their recorded stamps at a chosen rate"
CAMERA_SUFFIXES = ("/image_raw", "/camera_info", "/instance_mask", "/image_rect")


def qos_for(topic: str, message_count: int):
    """The QoS DESIGN.md gives each recorded topic."""
    if topic == "/tf_static":
        return QoSProfile(
            depth=max(1, message_count),
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
    if topic.endswith(CAMERA_SUFFIXES):
        return SENSOR_QOS
    return STREAM_QOS


class BagReplayNode(Node):
    """Publishes a bag in a background thread; ``done`` completes when replay is over."""

    def __init__(self) -> None:
        super().__init__(NAME)
        self.config: ReplayConfig = declare_config(self, ReplayConfig)
        if not self.config.bag:
            raise ValueError("parameter 'bag' is required: the rosbag2 directory to replay")
        topics = list_topics(self.config.bag)
        wanted = set(self.config.topics) or set(topics)
        missing = sorted(wanted - set(topics))
        if missing:
            raise ValueError(f"{self.config.bag}: topics not in the bag: {', '.join(missing)}")
        types = rclpy_types()
        self._outputs = {
            topic: self.create_publisher(
                types.get(info.msgtype), topic, qos_for(topic, info.message_count)
            )
            for topic, info in sorted(topics.items())
            if topic in wanted
        }
        self.done = Future()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="replay", daemon=True)
        self._thread.start()

    def _wait_for_subscribers(self) -> None:
        wanted = self.config.wait_for_subscribers
        if wanted <= 0:
            return
        images = [p for t, p in self._outputs.items() if t.endswith("/image_raw")]
        deadline = time.monotonic() + self.config.wait_timeout
        while any(p.get_subscription_count() < wanted for p in images):
            if time.monotonic() > deadline:
                self.get_logger().warning(
                    f"fewer than {wanted} subscriber(s) on the image topics after "
                    f"{self.config.wait_timeout:.1f} s; replaying anyway"
                )
                return
            if self._stop.wait(0.05):
                return
        self.get_logger().info(f"every image topic has {wanted} subscriber(s)")

    def _replay_once(self) -> int:
        count = 0
        messages = (m for m in iter_raw_messages(self.config.bag) if m.topic in self._outputs)
        for message in paced(messages, lambda m: m.log_time_ns, self.config.rate, stop=self._stop):
            self._outputs[message.topic].publish(message.data)
            count += 1
        return count

    def _run(self) -> None:
        try:
            self._wait_for_subscribers()
            if self._stop.wait(self.config.start_delay):
                return
            self.get_logger().info(
                f"replaying {self.config.bag}: {len(self._outputs)} topics at rate "
                f"{self.config.rate:g}" + (" (as fast as possible)" if self.config.rate == 0 else "")
            )
            while not self._stop.is_set():
                started = time.monotonic()
                count = self._replay_once()
                self.get_logger().info(
                    f"replayed {count} messages in {time.monotonic() - started:.2f} s"
                )
                if not self.config.loop:
                    break
            if self.config.exit_when_done:
                self._stop.wait(self.config.linger)
                self.done.set_result(True)
        except Exception as error:  # the thread must report, not die silently
            self.get_logger().error(f"replay failed: {error}")
            self.done.set_result(False)

    def destroy_node(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return main_for(NAME, ReplayConfig, BagReplayNode, SUMMARY, args)


if __name__ == "__main__":
    raise SystemExit(main())
