"""reconstruction_node: camera topics in, per-object observed geometry per frame out (stage 1).

Subscribes to every camera's color image, instance mask, optional depth and CameraInfo (the
sensor-data QoS) and to ``/tf_static``; assembles each camera's frames and groups the cameras'
frames by stamp with the core's matcher. Each complete frame set is logged; the per-object
reconstruction that will publish ``/mosiv/observed_objects`` plugs in at ``_on_frame_set``.
"""

from __future__ import annotations

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from tf2_msgs.msg import TFMessage

from mosiv_ros.config import ReconstructionConfig
from mosiv_ros.io.messages import (
    camera_info_from_msg,
    image_from_msg,
    stamp_to_ns,
    transform_from_msg,
)
from mosiv_ros.io.recording import FrameMatcher, FrameSet
from mosiv_ros.io.scene import Scene, load_scene
from mosiv_ros.io.streams import CameraFrameAssembler, mask_pixel_counts
from mosiv_ros.nodes.common import SENSOR_QOS, STREAM_QOS, declare_config, guarded, main_for

NAME = "reconstruction_node"
SUMMARY = "group multi-camera frames by stamp and reconstruct each object's geometry per frame"
IMAGE_TOPICS = {"rgb": "color/image_raw", "mask": "instance_mask", "depth": "depth/image_rect"}
TF_STATIC_QOS = QoSProfile(
    depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)


class ReconstructionNode(Node):
    """Thin shell: messages to the core's assemblers and matcher, frame sets to stage 1."""

    def __init__(self) -> None:
        super().__init__(NAME)
        self.config: ReconstructionConfig = declare_config(self, ReconstructionConfig)
        self.scene: Scene | None = load_scene(self.config.scene) if self.config.scene else None
        self.observed_pub = self.create_publisher(PointCloud2, "/mosiv/observed_objects", STREAM_QOS)
        self.assemblers: dict[str, CameraFrameAssembler] = {}
        self.extrinsics: dict[str, object] = {}
        self.matcher: FrameMatcher | None = None
        self.frame_sets = 0
        self.t0_ns: int | None = None
        self.create_subscription(TFMessage, "/tf_static", self._on_tf_static, TF_STATIC_QOS)
        if self.config.cameras:
            self._add_cameras(self.config.cameras)
        else:
            self.create_timer(0.25, self._discover_cameras)
        self.get_logger().info(
            "waiting for cameras "
            + (", ".join(self.config.cameras) if self.config.cameras else "(discovering)")
        )

    def _discover_cameras(self) -> None:
        found = {
            topic.split("/")[1]
            for topic, _ in self.get_topic_names_and_types()
            if topic.endswith("/" + IMAGE_TOPICS["rgb"]) and topic.count("/") == 3
        }
        new = sorted(found - set(self.assemblers))
        if new:
            self._add_cameras(new)

    def _add_cameras(self, cameras: list[str]) -> None:
        topics = {name for name, _ in self.get_topic_names_and_types()}
        for camera in cameras:
            depth_topic = f"/{camera}/{IMAGE_TOPICS['depth']}"
            expect_depth = self.config.use_depth and depth_topic in topics
            self.assemblers[camera] = CameraFrameAssembler(camera, expect_depth=expect_depth)
            for kind, suffix in IMAGE_TOPICS.items():
                if kind == "depth" and not expect_depth:
                    continue
                topic = f"/{camera}/{suffix}"
                self.create_subscription(
                    Image, topic, guarded(self, topic, self._image_converter(camera, kind),
                                          self._on_frame), SENSOR_QOS)
            info_topic = f"/{camera}/color/camera_info"
            self.create_subscription(
                CameraInfo, info_topic,
                guarded(self, info_topic, camera_info_from_msg, self._intrinsics_setter(camera)),
                SENSOR_QOS)
        tolerance_ns = int(round(self.config.sync_tolerance * 1e9))
        self.matcher = FrameMatcher(sorted(self.assemblers), tolerance_ns)
        self.get_logger().info(
            f"subscribed to cameras {', '.join(sorted(self.assemblers))} "
            f"(depth: {', '.join(c for c, a in sorted(self.assemblers.items()) if a.expect_depth) or 'none'})"
        )

    def _image_converter(self, camera: str, kind: str):
        assembler = self.assemblers

        def convert(msg: Image):
            frame = assembler[camera].add(kind, stamp_to_ns(msg.header.stamp), image_from_msg(msg))
            return (camera, frame)

        return convert

    def _intrinsics_setter(self, camera: str):
        def store(intrinsics) -> None:
            self.assemblers[camera].intrinsics = intrinsics

        return store

    def _on_tf_static(self, msg: TFMessage) -> None:
        for transform in msg.transforms:
            parent, child, matrix = transform_from_msg(transform)
            self.extrinsics[child] = (parent, matrix)

    def _on_frame(self, camera_frame) -> None:
        camera, frame = camera_frame
        if frame is None or self.matcher is None:
            return
        for frame_set in self.matcher.add(camera, frame):
            self._on_frame_set(frame_set)

    def _on_frame_set(self, frame_set: FrameSet) -> None:
        self.frame_sets += 1
        if self.t0_ns is None:
            self.t0_ns = frame_set.stamp_ns
        pixels = mask_pixel_counts(frame_set.frames.values())
        objects = ", ".join(f"{i} ({n} px)" for i, n in sorted(pixels.items())) or "none"
        self.get_logger().info(
            f"frame set {self.frame_sets}: t={(frame_set.stamp_ns - self.t0_ns) * 1e-9:.3f} s "
            f"stamp {frame_set.stamp_ns} ns, cameras {', '.join(sorted(frame_set.frames))}, "
            f"objects {objects}"
        )
        if self.scene is not None:
            declared = {o.id for o in self.scene.objects}
            unknown = sorted(set(pixels) - declared)
            if unknown:
                self.get_logger().warning(
                    f"frame set {self.frame_sets}: mask ids {unknown} are not declared in the scene"
                )


def main(args: list[str] | None = None) -> int:
    return main_for(NAME, ReconstructionConfig, ReconstructionNode, SUMMARY, args)


if __name__ == "__main__":
    raise SystemExit(main())
