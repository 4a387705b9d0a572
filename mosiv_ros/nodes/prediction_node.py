"""prediction_node: identified twin in, predicted object dynamics out, for planners.

Subscribes to ``/mosiv/particles`` and ``/mosiv/material_estimates`` (both latched; or takes the
estimates from its parameter ``estimates``, which identify_node's estimates file sets:
``--params-file FILE``), and to ``/gripper/pose`` with ``/tf_static`` (a declared gripper moves
along the poses received when the twin is built, and holds its last pose past them; poses that
arrive later are used once none came for ``GRIPPER_SETTLE_S``, with a new prediction). With both,
it rolls the core's ``Twin`` from the first observed frame to
``horizon`` seconds past the fitted window and publishes, latched so that a planner joining
later still gets them:

- ``/mosiv/predicted_objects``: sensor_msgs/PointCloud2 of every predicted frame after the
  window, fields x, y, z, object_id and ``t`` (seconds after the header stamp, the window's end);
- ``/mosiv/predicted_paths/<object>``: nav_msgs/Path of each object's predicted centroid;
- ``/mosiv/predicted_markers``: visualization_msgs/MarkerArray of those paths.

What-if requests (parameters ``initial_velocities``, ``swapped_params``; see
``predict.request``) roll the twin from the first observed frame with new initial velocities or
parameters, and the same topics then carry every frame from the first observed one (header
stamp) on. ``ros2 param set`` changes a request, the estimates, ``horizon`` or ``frame_rate`` at
run time; a value outside its range (``mosiv_ros.config``), a request naming an unknown object or
parameter, and a change of another parameter are refused with the reason, and the prediction is
redone after every accepted change.

Every new estimate replaces the prediction. Estimates with ERROR status are not rolled out.
"""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Path
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from mosiv_ros.config import PredictionConfig
from mosiv_ros.identify.estimates import ERROR, Estimates
from mosiv_ros.io.bag import load_scene
from mosiv_ros.io.messages import pointcloud_to_msg, rclpy_types
from mosiv_ros.io.scene import Scene
from mosiv_ros.lifting.lift import LiftedParticles
from mosiv_ros.nodes.common import (
    LATCHED_QOS,
    declare_config,
    gripper_poses,
    guarded,
    lifted_from_msg,
    main_for,
    world_gripper_poses,
)
from mosiv_ros.nodes.outputs import markers_msg, path_msg, statuses_of
from mosiv_ros.predict.request import WhatIf
from mosiv_ros.predict.twin import Twin
from mosiv_ros.sim.errors import SimulationError
from mosiv_ros.sim.runtime import resolve_device

NAME = "prediction_node"
SUMMARY = "roll the identified digital twin forward and publish predicted object dynamics"
GRIPPER_SETTLE_S = 0.5
"""Seconds without a new gripper pose (or transform) before a prediction is redone with them."""


class PredictionNode(Node):
    """Thin shell: particles + estimates (+ a what-if request) to the core's ``Twin``, predictions out."""

    def __init__(self) -> None:
        super().__init__(NAME)
        self.config: PredictionConfig = declare_config(self, PredictionConfig, self._check_change)
        resolve_device(self.config.device)  # a device that is not there stops the node now
        self.scene: Scene = load_scene(self.config.scene) if self.config.scene else Scene()
        self.request = WhatIf.parse(self.config.initial_velocities, self.config.swapped_params)
        self.types = rclpy_types()
        self.predicted_pub = self.create_publisher(PointCloud2, "/mosiv/predicted_objects", LATCHED_QOS)
        self.markers_pub = self.create_publisher(MarkerArray, "/mosiv/predicted_markers", LATCHED_QOS)
        self.path_pubs: dict[str, object] = {}
        self.particles: LiftedParticles | None = None
        self.estimates: Estimates | None = None
        self.twin: Twin | None = None
        self.accepted: tuple[PredictionConfig, Estimates | None, WhatIf] | None = None
        self.redo = None
        self.gripper = gripper_poses(self, self._on_gripper)
        self.gripper_changed: float | None = None  # when poses last arrived after the twin was built
        self.create_timer(GRIPPER_SETTLE_S / 2, self._gripper_settled)
        self.create_subscription(
            PointCloud2, "/mosiv/particles",
            guarded(self, "/mosiv/particles", lifted_from_msg, self._on_particles), LATCHED_QOS)
        self.create_subscription(
            DiagnosticArray, "/mosiv/material_estimates",
            guarded(self, "/mosiv/material_estimates",
                    lambda msg: Estimates.from_statuses(statuses_of(msg)), self._on_estimates),
            LATCHED_QOS)
        self.add_post_set_parameters_callback(self._on_changed)
        if self.config.estimates:
            self._on_estimates(Estimates.from_yaml(self.config.estimates))

    def _on_gripper(self) -> None:
        if self.twin is not None and self.scene.gripper is not None:
            self.gripper_changed = time.monotonic()

    def _gripper_settled(self) -> None:
        """Once no gripper pose came for GRIPPER_SETTLE_S, predict again with the poses received."""
        if self.gripper_changed is None or time.monotonic() - self.gripper_changed < GRIPPER_SETTLE_S:
            return
        self.gripper_changed, self.twin = None, None
        self._predict()

    def _on_particles(self, particles: LiftedParticles) -> None:
        self.particles, self.twin = particles, None
        self._predict()

    def _on_estimates(self, estimates: Estimates) -> None:
        unusable = _unusable(estimates)
        if unusable:
            self.get_logger().warning(f"{unusable}; no prediction")
            return
        self.estimates, self.twin = estimates, None
        self._predict()

    def _check_change(self, config: PredictionConfig, changed: dict) -> None:
        """ValueError if a run-time change (in range) gives estimates or a request that cannot be used."""
        estimates = self.estimates
        if changed.get("estimates"):
            estimates = Estimates.from_yaml(config.estimates)
            if _unusable(estimates):
                raise ValueError(_unusable(estimates))
        request = WhatIf.parse(config.initial_velocities, config.swapped_params)
        if estimates is not None:
            request.check({o.name: o.family for o in estimates.objects})
        self.accepted = (config, estimates, request)

    def _on_changed(self, _params: list[Parameter]) -> None:
        """After an accepted change: use it, and predict again once the set call has returned."""
        self.config, estimates, self.request = self.accepted
        if estimates is not self.estimates:
            self.estimates, self.twin = estimates, None
        if self.redo is None:
            self.redo = self.create_timer(0.01, self._predict_again)

    def _predict_again(self) -> None:
        self.destroy_timer(self.redo)
        self.redo = None
        self._predict()

    def _predict(self) -> None:
        if self.particles is None or self.estimates is None:
            return
        try:
            if self.twin is None:
                self.twin = Twin(self.particles, self.estimates, self.scene, device=self.config.device,
                                 gripper_poses=world_gripper_poses(self, self.gripper))
            if self.request:
                future = self.twin.what_if(self.request, self.config.horizon, self.config.frame_rate)
            else:
                future = self.twin.future(self.config.horizon, self.config.frame_rate)
        except (ValueError, RuntimeError, SimulationError) as error:
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
        what_if = f" (what-if: {self.request.describe()})" if self.request else ""
        self.get_logger().info(
            f"predicted {len(stamps)} frames ({future.times[0]:.2f}..{future.times[-1]:.2f} s after "
            f"the first observed frame) for {', '.join(future.names)}{what_if}")


def _unusable(estimates: Estimates) -> str:
    """Why estimates cannot be rolled out ('' if they can)."""
    failed = [o.name for o in estimates.objects if o.level == ERROR]
    return f"estimates unusable (failed: {failed or 'no objects'})" if failed or not estimates.objects else ""


def main(args: list[str] | None = None) -> int:
    return main_for(NAME, PredictionConfig, PredictionNode, SUMMARY, args)


if __name__ == "__main__":
    raise SystemExit(main())
