"""lifting_node: the first complete observed frame in, simulation particles out (stage 2).

Subscribes to ``/mosiv/observed_objects``; lifts the first frame in which every declared object
(parameter ``scene``) has an occupied voxel (without a declaration: the first frame with any) with
the core's ``lift``, and publishes the particles once on ``/mosiv/particles``, latched (reliable +
transient_local): a PointCloud2 in ``world`` with fields x, y, z, volume, sdf, lattice_volume
(float32), object_id, segment (uint16), material (uint8, the family's index in
``mosiv_ros.io.scene.FAMILIES``, 255 = family not declared), and boundary_beta, boundary_eps
(float64: the node's parameters, which the consumers' boundary volumes use). Where an image
border cuts an object of the first complete frame (field ``cut``), the first of the next
``border_wait`` frames that none cuts is lifted instead (``mosiv_ros.lifting.lift_choice``). The
next ``consensus_frames`` clouds trim each object's hull first (``mosiv_ros.lifting.consensus``):
the node lifts once they have come, or ``consensus_timeout`` seconds after the first complete
frame with those that did. Later frames are ignored.
"""

from __future__ import annotations

import time

from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from mosiv_ros.config import LiftingConfig
from mosiv_ros.io.bag import load_scene
from mosiv_ros.io.messages import pointcloud_from_msg, pointcloud_to_msg, rclpy_types
from mosiv_ros.io.recording import PointCloud
from mosiv_ros.io.scene import Scene
from mosiv_ros.lifting import border_note, lift, lift_choice, missing_objects
from mosiv_ros.nodes.common import LATCHED_QOS, STREAM_QOS, declare_config, guarded, main_for
from mosiv_ros.recon import VOXEL_FIELD

NAME = "lifting_node"
SUMMARY = "fill each object's first observed frame with simulation particles (latched output)"
TOPIC = "/mosiv/observed_objects"


class LiftingNode(Node):
    """Thin shell: the first complete observed cloud to the core's ``lift``, particles out."""

    def __init__(self) -> None:
        super().__init__(NAME)
        self.config: LiftingConfig = declare_config(self, LiftingConfig)
        self.scene: Scene | None = load_scene(self.config.scene) if self.config.scene else None
        self.types = rclpy_types()
        self.particles_pub = self.create_publisher(PointCloud2, "/mosiv/particles", LATCHED_QOS)
        self.lifted_stamp: int | None = None
        self.clouds: list[PointCloud] = []  # from the first complete frame on, until the lift
        self.chosen: int | None = None  # which of them to lift, once known
        self.first_time = 0.0
        self.create_timer(0.1, self._lift_on_timeout)
        self.create_subscription(
            PointCloud2, TOPIC, guarded(self, TOPIC, pointcloud_from_msg, self._on_observed), STREAM_QOS)
        declared = ", ".join(str(i) for i in self.scene.ids) if self.scene and self.scene.ids else "any"
        self.get_logger().info(f"waiting for an observed frame with objects: {declared}")

    def _on_observed(self, cloud: PointCloud) -> None:
        if self.lifted_stamp is not None:
            return
        if self.clouds:
            if VOXEL_FIELD not in cloud.fields:
                self.get_logger().warning(f"{TOPIC} stamp {cloud.stamp_ns} ns: no {VOXEL_FIELD!r} field; "
                                          "not used to trim the lifted frame")
                return
            if cloud.stamp_ns <= self.clouds[-1].stamp_ns:
                return
            self.clouds.append(cloud)
        else:
            missing = missing_objects(cloud, self.scene)
            if missing:
                self.get_logger().warning(
                    f"{TOPIC} stamp {cloud.stamp_ns} ns: objects {missing} not observed; waiting for a "
                    "frame with every declared object")
                return
            self.clouds, self.first_time = [cloud], time.monotonic()
        if self.chosen is None:
            self.chosen = lift_choice(self.clouds, self.scene, self.config.border_wait)
        if self.chosen is not None and len(self.clouds) - self.chosen - 1 >= self.config.consensus_frames:
            self._lift()

    def _lift_on_timeout(self) -> None:
        if (self.clouds and self.lifted_stamp is None
                and time.monotonic() - self.first_time > self.config.consensus_timeout):
            later = len(self.clouds) - (self.chosen or 0) - 1
            self.get_logger().warning(
                f"{later} of {self.config.consensus_frames} later frames came within "
                f"{self.config.consensus_timeout} s of stamp {self.clouds[0].stamp_ns} ns; lifting with those")
            self._lift()

    def _lift(self) -> None:
        chosen = self.chosen or 0
        cloud, later = self.clouds[chosen], self.clouds[chosen + 1:chosen + 1 + self.config.consensus_frames]
        note = border_note(self.clouds, chosen)
        if note:
            self.get_logger().warning(f"{TOPIC} {note}")
        self.clouds, self.chosen = [], None
        try:
            lifted = lift(cloud, self.config, self.scene, later)
        except ValueError as error:
            self.get_logger().error(f"{TOPIC} stamp {cloud.stamp_ns} ns: not lifted: {error}")
            return
        for message in lifted.warnings:
            self.get_logger().warning(message)
        particles = lifted.to_cloud()
        self.particles_pub.publish(pointcloud_to_msg(
            self.types, particles.xyz, particles.object_id, particles.stamp_ns, "world", particles.fields))
        self.lifted_stamp = cloud.stamp_ns
        self.get_logger().info(f"published particles of stamp {cloud.stamp_ns} ns: {lifted.summary()}")


def main(args: list[str] | None = None) -> int:
    return main_for(NAME, LiftingConfig, LiftingNode, SUMMARY, args)


if __name__ == "__main__":
    raise SystemExit(main())
