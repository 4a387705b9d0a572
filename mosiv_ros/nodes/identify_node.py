"""identify_node: observed geometry and particles in, per-object material estimates out (stage 3).

Subscribes to ``/mosiv/observed_objects`` and ``/mosiv/particles`` (latched); publishes
``/mosiv/material_estimates`` (diagnostic_msgs/DiagnosticArray, latched) and progress on
``/diagnostics``. Until the identification core exists it logs what it receives.
"""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from mosiv_ros.config import IdentifyConfig
from mosiv_ros.io.messages import pointcloud_from_msg
from mosiv_ros.nodes.common import (
    LATCHED_QOS,
    STREAM_QOS,
    declare_config,
    guarded,
    log_cloud,
    main_for,
)

NAME = "identify_node"
SUMMARY = "fit per-object material parameters with the differentiable MPM simulator"


class IdentifyNode(Node):
    def __init__(self) -> None:
        super().__init__(NAME)
        self.config: IdentifyConfig = declare_config(self, IdentifyConfig)
        self.estimates_pub = self.create_publisher(
            DiagnosticArray, "/mosiv/material_estimates", LATCHED_QOS)
        self.progress_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        for topic, qos in (("/mosiv/observed_objects", STREAM_QOS), ("/mosiv/particles", LATCHED_QOS)):
            self.create_subscription(
                PointCloud2, topic,
                guarded(self, topic, pointcloud_from_msg, lambda c, t=topic: log_cloud(self, t, c)),
                qos)


def main(args: list[str] | None = None) -> int:
    return main_for(NAME, IdentifyConfig, IdentifyNode, SUMMARY, args)


if __name__ == "__main__":
    raise SystemExit(main())
