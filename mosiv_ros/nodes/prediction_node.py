"""prediction_node: identified twin in, predicted object dynamics out, for planners.

Subscribes to ``/mosiv/particles`` and ``/mosiv/material_estimates`` (both latched); publishes
``/mosiv/predicted_objects`` (PointCloud2 with ``t``), ``/mosiv/predicted_paths/<object>``
(nav_msgs/Path, created per object once the objects are known) and ``/mosiv/predicted_markers``.
Until the prediction core exists it logs what it receives.
"""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from mosiv_ros.config import PredictionConfig
from mosiv_ros.io.messages import pointcloud_from_msg
from mosiv_ros.nodes.common import (
    LATCHED_QOS,
    STREAM_QOS,
    declare_config,
    guarded,
    log_cloud,
    main_for,
)

NAME = "prediction_node"
SUMMARY = "roll the identified digital twin forward and publish predicted object dynamics"


class PredictionNode(Node):
    def __init__(self) -> None:
        super().__init__(NAME)
        self.config: PredictionConfig = declare_config(self, PredictionConfig)
        self.predicted_pub = self.create_publisher(
            PointCloud2, "/mosiv/predicted_objects", STREAM_QOS)
        self.markers_pub = self.create_publisher(MarkerArray, "/mosiv/predicted_markers", 10)
        self.path_pubs: dict[str, object] = {}
        topic = "/mosiv/particles"
        self.create_subscription(
            PointCloud2, topic,
            guarded(self, topic, pointcloud_from_msg, lambda c: log_cloud(self, topic, c)),
            LATCHED_QOS)
        self.create_subscription(
            DiagnosticArray, "/mosiv/material_estimates", self._on_estimates, LATCHED_QOS)

    def _on_estimates(self, msg: DiagnosticArray) -> None:
        names = ", ".join(status.name for status in msg.status) or "none"
        self.get_logger().info(f"/mosiv/material_estimates: estimates for {names}")


def main(args: list[str] | None = None) -> int:
    return main_for(NAME, PredictionConfig, PredictionNode, SUMMARY, args)


if __name__ == "__main__":
    raise SystemExit(main())
