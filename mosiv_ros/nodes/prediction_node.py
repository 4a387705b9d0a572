"""prediction_node: identified twin in, predicted object dynamics out, for planners.

Subscribes to ``/mosiv/particles`` and ``/mosiv/material_estimates`` (both latched; or reads the
estimates from ``estimates_file``). With both, it rolls the core's ``Twin`` from the first
observed frame to ``horizon`` seconds past the fitted window and publishes, latched so that a
planner joining later still gets them:

- ``/mosiv/predicted_objects``: sensor_msgs/PointCloud2 of every predicted frame after the
  window, fields x, y, z, object_id and ``t`` (seconds after the header stamp, the window's end);
- ``/mosiv/predicted_paths/<object>``: nav_msgs/Path of each object's predicted centroid;
- ``/mosiv/predicted_markers``: visualization_msgs/MarkerArray of those paths.

Every new estimate replaces the prediction. Estimates with ERROR status are not rolled out.
"""

from __future__ import annotations

import threading

from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Path
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from mosiv_ros.config import PredictionConfig
from mosiv_ros.identify.estimates import ERROR, Estimates
from mosiv_ros.io.messages import pointcloud_to_msg, rclpy_types
from mosiv_ros.io.scene import Scene, load_scene
from mosiv_ros.lifting.lift import LiftedParticles
from mosiv_ros.nodes.common import LATCHED_QOS, declare_config, guarded, lifted_from_msg, main_for
from mosiv_ros.nodes.outputs import markers_msg, path_msg, statuses_of
from mosiv_ros.predict.twin import Twin

NAME = "prediction_node"
SUMMARY = "roll the identified digital twin forward and publish predicted object dynamics"


class PredictionNode(Node):
    """Thin shell: particles + estimates to the core's ``Twin``, predictions out."""

    def __init__(self) -> None:
        super().__init__(NAME)
        self.config: PredictionConfig = declare_config(self, PredictionConfig)
        self.scene: Scene = load_scene(self.config.scene) if self.config.scene else Scene()
        self.types = rclpy_types()
        self.predicted_pub = self.create_publisher(PointCloud2, "/mosiv/predicted_objects", LATCHED_QOS)
        self.markers_pub = self.create_publisher(MarkerArray, "/mosiv/predicted_markers", LATCHED_QOS)
        self.path_pubs: dict[str, object] = {}
        self.particles: LiftedParticles | None = None
        self.estimates: Estimates | None = None
        self.lock = threading.Lock()
        self.create_subscription(
            PointCloud2, "/mosiv/particles",
            guarded(self, "/mosiv/particles", lifted_from_msg, self._on_particles), LATCHED_QOS)
        self.create_subscription(
            DiagnosticArray, "/mosiv/material_estimates",
            guarded(self, "/mosiv/material_estimates",
                    lambda msg: Estimates.from_statuses(statuses_of(msg)), self._on_estimates),
            LATCHED_QOS)
        if self.config.estimates_file:
            self._on_estimates(Estimates.read(self.config.estimates_file))

    def _on_particles(self, particles: LiftedParticles) -> None:
        self.particles = particles
        self._predict()

    def _on_estimates(self, estimates: Estimates) -> None:
        failed = [o.name for o in estimates.objects if o.level == ERROR]
        if failed or not estimates.objects:
            self.get_logger().warning(f"estimates unusable (failed: {failed or 'no objects'}); no prediction")
            return
        self.estimates = estimates
        self._predict()

    def _predict(self) -> None:
        with self.lock:
            if self.particles is None or self.estimates is None:
                return
            try:
                twin = Twin(self.particles, self.estimates, self.scene, device=self.config.device)
                future = twin.future(self.config.horizon, self.config.frame_rate)
            except (ValueError, RuntimeError) as error:
                self.get_logger().error(f"prediction failed: {error}")
                return
        if not len(future.times):
            self.get_logger().warning("the prediction has no frame past the observed window")
            return
        stamps = future.stamps_ns()
        cloud = future.to_cloud(stamps[0])
        self.predicted_pub.publish(pointcloud_to_msg(self.types, cloud.xyz, cloud.object_id, cloud.stamp_ns,
                                                     cloud.frame_id, cloud.fields))
        centroids = future.centroids()
        for k, name in enumerate(future.names):
            if name not in self.path_pubs:
                self.path_pubs[name] = self.create_publisher(Path, f"/mosiv/predicted_paths/{name}",
                                                             LATCHED_QOS)
            self.path_pubs[name].publish(path_msg(stamps, centroids[:, k]))
        self.markers_pub.publish(markers_msg(future.names, centroids, stamps[0]))
        self.get_logger().info(
            f"predicted {len(stamps)} frames ({future.times[0]:.2f}..{future.times[-1]:.2f} s after "
            f"the first observed frame) for {', '.join(future.names)}")


def main(args: list[str] | None = None) -> int:
    return main_for(NAME, PredictionConfig, PredictionNode, SUMMARY, args)


if __name__ == "__main__":
    raise SystemExit(main())
