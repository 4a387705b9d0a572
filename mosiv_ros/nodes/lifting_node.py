"""lifting_node: the first complete observed frame in, simulation particles out (stage 2).

Subscribes to ``/mosiv/observed_objects``; publishes ``/mosiv/particles`` latched (reliable +
transient_local). Until the lifting core exists it logs each observed frame it receives.
"""

from __future__ import annotations

from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from mosiv_ros.config import LiftingConfig
from mosiv_ros.io.messages import pointcloud_from_msg
from mosiv_ros.nodes.common import (
    LATCHED_QOS,
    STREAM_QOS,
    declare_config,
    guarded,
    log_cloud,
    main_for,
)

NAME = "lifting_node"
SUMMARY = "fill each object's first observed frame with simulation particles (latched output)"


class LiftingNode(Node):
    def __init__(self) -> None:
        super().__init__(NAME)
        self.config: LiftingConfig = declare_config(self, LiftingConfig)
        self.particles_pub = self.create_publisher(PointCloud2, "/mosiv/particles", LATCHED_QOS)
        topic = "/mosiv/observed_objects"
        self.create_subscription(
            PointCloud2, topic,
            guarded(self, topic, pointcloud_from_msg, lambda c: log_cloud(self, topic, c)),
            STREAM_QOS)


def main(args: list[str] | None = None) -> int:
    return main_for(NAME, LiftingConfig, LiftingNode, SUMMARY, args)


if __name__ == "__main__":
    raise SystemExit(main())
