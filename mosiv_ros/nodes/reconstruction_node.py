"""reconstruction_node: camera topics in, per-object observed geometry per frame out (stage 1).

Subscribes to every camera's color image, instance mask, optional depth and CameraInfo (the
sensor-data QoS), to ``/tf_static`` and, for a scene that declares a gripper, to ``/gripper/pose``
(the gripper at each set's stamp hides what lies behind it, ``recon.gripper``; a set waits for the
pose at its stamp as it waits for a late camera); assembles each camera's frames and groups the cameras'
frames by stamp with the core's matcher. Each frame set goes to the core's ``Reconstructor``;
the result is published on ``/mosiv/observed_objects``: a PointCloud2 in ``world`` with fields
x, y, z (float32), object_id (uint16), voxel_size (float32: the edge of the voxel a point is
the centre of, 0 for a surface point) and rgb (uint32 0x00RRGGBB, a surface point's colour), one
message per frame set stamped with the set's stamp. The surface tracks alive at each set go on
``/mosiv/surface_tracks`` (x, y, z, object_id, track_id uint32, confidence float32), one cloud per
set with the same stamp; one tracker follows them across the whole stream.

A frame set still lacking some cameras is reconstructed from the others (with a warning) once a
later set completes or ``partial_set_timeout`` has passed, so a camera that stops publishing
degrades the result instead of stopping it (and when the stream goes quiet for that long, the sets
still pending are reconstructed too). Sets that arrive before their cameras' CameraInfo and
``/tf_static`` wait for them. Reconstruction runs in a worker thread, in stamp order, so that
slow frames do not make the image callbacks drop messages; a growing backlog is reported.
"""

from __future__ import annotations

import queue
import threading
import time

from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from tf2_msgs.msg import TFMessage

from mosiv_ros.config import ReconstructionConfig
from mosiv_ros.io.bag import load_scene
from mosiv_ros.io.messages import (
    camera_image_from_msg,
    camera_info_from_msg,
    pointcloud_to_msg,
    rclpy_types,
    stamp_to_ns,
    transform_from_msg,
)
from mosiv_ros.io.recording import Camera, FrameMatcher, FrameSet
from mosiv_ros.io.scene import Scene
from mosiv_ros.io.streams import CameraFrameAssembler, mask_pixel_counts
from mosiv_ros.io.transforms import WORLD_FRAME, StaticTransforms
from mosiv_ros.nodes.common import (
    STREAM_QOS,
    TF_STATIC_QOS,
    declare_config,
    gripper_poses,
    guarded,
    main_for,
    sensor_qos,
)
from mosiv_ros.recon import Reconstructor, SurfaceTracker
from mosiv_ros.recon.gripper import gripper_at

NAME = "reconstruction_node"
SUMMARY = "group multi-camera frames by stamp and reconstruct each object's geometry per frame"
TRACKS_TOPIC = "/mosiv/surface_tracks"
IMAGE_TOPICS = {"mask": "instance_mask", "depth": "depth/image_rect", "rgb": "color/image_raw"}
"""A camera's image topics, subscribed in this order: the colour image, on whose subscription a replay
waits, last."""
MAX_UNCALIBRATED = 30
"""Frame sets kept while waiting for calibration; older ones are dropped with a warning."""
BACKLOG_WARNING = 10


class ReconstructionNode(Node):
    """Thin shell: messages to the core's assemblers and matcher, frame sets to stage 1."""

    def __init__(self) -> None:
        super().__init__(NAME)
        self.config: ReconstructionConfig = declare_config(self, ReconstructionConfig)
        self.scene: Scene | None = load_scene(self.config.scene) if self.config.scene else None
        self.types = rclpy_types()
        self.observed_pub = self.create_publisher(PointCloud2, "/mosiv/observed_objects", STREAM_QOS)
        self.tracks_pub = self.create_publisher(PointCloud2, TRACKS_TOPIC, STREAM_QOS)
        self.tracker = SurfaceTracker(self.config.tracks)
        self.assemblers: dict[str, CameraFrameAssembler] = {}
        self.transforms = StaticTransforms()
        self.matcher: FrameMatcher | None = None
        self.reconstructor: Reconstructor | None = None
        self.uncalibrated: list[FrameSet] = []  # sets waiting, in order, for their calibration
        # Reconstruction runs in a worker thread so that the callbacks keep taking images in.
        self.work: queue.Queue[FrameSet | None] = queue.Queue()
        self.worker = threading.Thread(target=self._work, name="reconstruction", daemon=True)
        self.worker.start()
        self.newest_ns = 0
        self.frame_sets = 0
        self.published = 0
        self.seconds = 0.0
        self.t0_ns: int | None = None
        self.last_frame_time = time.monotonic()
        self.create_timer(0.1, self._flush_when_idle)
        self.create_subscription(TFMessage, "/tf_static", self._on_tf_static, TF_STATIC_QOS)
        # The worker waits on ``arrived`` for a set's gripper pose; each frame and pose notifies it.
        self.arrived = threading.Condition()
        self.last_pose_time = time.monotonic()
        self.gripper = gripper_poses(self, on_change=self._on_pose, transforms=self.transforms)
        self.warned_no_gripper = False
        self.warned_held_ns: int | None = None
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
        qos = sensor_qos(self.config.image_history)
        for camera in cameras:
            depth_topic = f"/{camera}/{IMAGE_TOPICS['depth']}"
            expect_depth = self.config.use_depth and depth_topic in topics
            self.assemblers[camera] = CameraFrameAssembler(camera, expect_depth=expect_depth)
            info_topic = f"/{camera}/color/camera_info"
            self.create_subscription(
                CameraInfo, info_topic,
                guarded(self, info_topic, camera_info_from_msg, self._intrinsics_setter(camera)), qos)
            for kind, suffix in IMAGE_TOPICS.items():
                if kind == "depth" and not expect_depth:
                    continue
                topic = f"/{camera}/{suffix}"
                self.create_subscription(
                    Image, topic, guarded(self, topic, self._image_converter(camera, kind),
                                          self._on_frame), qos)
        tolerance_ns = int(round(self.config.sync_tolerance * 1e9))
        self.matcher = FrameMatcher(sorted(self.assemblers), tolerance_ns, horizon_ns=None)
        self.reconstructor = None  # the rig changed: rebuilt at the next frame set
        self.get_logger().info(
            f"subscribed to cameras {', '.join(sorted(self.assemblers))} "
            f"(depth: {', '.join(c for c, a in sorted(self.assemblers.items()) if a.expect_depth) or 'none'})"
        )

    def _image_converter(self, camera: str, kind: str):
        assembler = self.assemblers

        def convert(msg: Image):
            frame = assembler[camera].add(kind, stamp_to_ns(msg.header.stamp), camera_image_from_msg(kind, msg))
            return (camera, frame)

        return convert

    def _intrinsics_setter(self, camera: str):
        def store(intrinsics) -> None:
            self.assemblers[camera].intrinsics = intrinsics
            self._drain_uncalibrated()

        return store

    def _on_tf_static(self, msg: TFMessage) -> None:
        for transform in msg.transforms:
            self.transforms.add(*transform_from_msg(transform))
        self._drain_uncalibrated()

    def _drain_uncalibrated(self) -> None:
        """Queue the sets that waited for calibration, in order, as far as it allows.

        Warns every BACKLOG_WARNING sets the worker falls behind.
        """
        while self.uncalibrated and self._calibrated(self.uncalibrated[0]):
            self.work.put(self.uncalibrated.pop(0))
            backlog = self.work.qsize()
            if backlog and backlog % BACKLOG_WARNING == 0:
                self.get_logger().warning(
                    f"reconstruction is {backlog} sets behind the cameras; consider a larger "
                    "voxel_size or fewer cameras")

    def _work(self) -> None:
        """The worker thread: reconstruct queued sets until None arrives."""
        while (frame_set := self.work.get()) is not None:
            self._reconstruct(frame_set)

    def destroy_node(self) -> None:
        self.work.put(None)
        self.worker.join(timeout=5.0)
        super().destroy_node()

    def _on_frame(self, camera_frame) -> None:
        camera, frame = camera_frame
        if frame is None or self.matcher is None:
            return
        with self.arrived:
            self.last_frame_time = time.monotonic()
            self.newest_ns = max(self.newest_ns, frame.stamp_ns)
            self.arrived.notify_all()
        complete = self.matcher.add(camera, frame)
        # Sets older than a completed one, or than the timeout, will not complete any more.
        cutoff = self.newest_ns - int(self.config.partial_set_timeout * 1e9)
        if complete:
            cutoff = max(cutoff, complete[0].stamp_ns)
        for frame_set in self.matcher.flush(before_ns=cutoff) + complete:
            self._on_frame_set(frame_set)

    def _flush_when_idle(self) -> None:
        """Timer: reconstruct the pending partial sets once the stream went quiet.

        After partial_set_timeout seconds without a frame, the sets still lacking a camera (the
        last ones of a stream that lost a camera) will not complete.
        """
        if self.matcher is None or not self.matcher.pending:
            return
        if time.monotonic() - self.last_frame_time > self.config.partial_set_timeout:
            for frame_set in self.matcher.flush():
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
        self.uncalibrated.append(frame_set)
        if len(self.uncalibrated) > MAX_UNCALIBRATED:
            dropped = self.uncalibrated.pop(0)
            self.get_logger().warning(
                f"stamp {dropped.stamp_ns} ns: not reconstructed: no calibration for "
                f"{', '.join(self._uncalibrated_cameras(dropped))} (needs CameraInfo and "
                f"/tf_static {WORLD_FRAME} -> <cam>_optical)")
        self._drain_uncalibrated()

    def _reconstruct(self, frame_set: FrameSet) -> None:
        try:
            observed = self._reconstructor(frame_set).reconstruct(frame_set, self._gripper_pose(frame_set.stamp_ns))
        except ValueError as error:
            self.get_logger().error(f"stamp {frame_set.stamp_ns} ns: not reconstructed: {error}")
            return
        for message in observed.warnings:
            self.get_logger().warning(message)
        for publisher, cloud in ((self.observed_pub, observed.to_cloud()),
                                 (self.tracks_pub, observed.tracks.to_cloud())):
            publisher.publish(pointcloud_to_msg(
                self.types, cloud.xyz, cloud.object_id, cloud.stamp_ns, WORLD_FRAME, cloud.fields))
        self.published += 1
        self.seconds += observed.seconds
        self.get_logger().info(
            f"published observed objects {self.published} (stamp {frame_set.stamp_ns} ns): "
            f"{observed.summary()}; mean {self.seconds / self.published * 1e3:.0f} ms per set")

    def _on_pose(self) -> None:
        with self.arrived:
            self.last_pose_time = time.monotonic()
            self.arrived.notify_all()

    def _gripper_pose(self, stamp_ns: int):
        """The declared gripper's pose at ``stamp_ns`` (None without one, or without poses).

        Waits (in the worker thread) for a pose at or after the stamp as a set waits for a late
        camera: until frames stamped ``partial_set_timeout`` past it have come (the pose stream
        lags), or nothing (frame or pose) has come for that long (the streams stopped). Both
        follow the streams, not the worker's wall clock, so a busy node waits no less. Past that,
        the poses so far: the last held, with a warning.
        """
        if self.scene is None or self.scene.gripper is None:
            return None
        timeout = self.config.partial_set_timeout
        with self.arrived:
            while True:
                poses = self.gripper.world()[0]
                if poses and poses[-1][0] >= stamp_ns:
                    return gripper_at(poses, stamp_ns)
                quiet = time.monotonic() - max(self.last_frame_time, self.last_pose_time)
                if self.newest_ns - stamp_ns > timeout * 1e9 or quiet >= timeout:
                    break
                self.arrived.wait(timeout - quiet)
        if not poses:
            if not self.warned_no_gripper:
                self.warned_no_gripper = True
                self.get_logger().warning(
                    f"stamp {stamp_ns} ns: the scene declares a gripper but no pose of it has come on "
                    "/gripper/pose: its pixels carve what lies behind it until one does")
        elif self.warned_held_ns != poses[-1][0]:  # once for each pose held
            self.warned_held_ns = poses[-1][0]
            self.get_logger().warning(
                f"stamp {stamp_ns} ns: no /gripper/pose at or after it within partial_set_timeout "
                f"({timeout} s of the streams): the gripper held at its pose of stamp {poses[-1][0]} ns "
                "(a pose stream slower than that needs a longer partial_set_timeout)")
        return gripper_at(poses, stamp_ns)

    def _uncalibrated_cameras(self, frame_set: FrameSet) -> list[str]:
        return [name for name in sorted(frame_set.frames)
                if self.assemblers[name].intrinsics is None or self.transforms.to_world(f"{name}_optical") is None]

    def _calibrated(self, frame_set: FrameSet) -> bool:
        return not self._uncalibrated_cameras(frame_set)

    def _reconstructor(self, frame_set: FrameSet) -> Reconstructor:
        """The stage-1 core for every calibrated camera, rebuilt when a set brings a new one."""
        if self.reconstructor is not None and set(frame_set.frames) <= set(self.reconstructor.cameras):
            return self.reconstructor
        cameras = {}
        for name in sorted(self.assemblers):
            intrinsics = self.assemblers[name].intrinsics
            pose = self.transforms.to_world(f"{name}_optical")
            if intrinsics is not None and pose is not None:
                cameras[name] = Camera(name, intrinsics, pose)
        self.reconstructor = Reconstructor(cameras, self.config, self.scene, self.tracker)
        lattice = self.reconstructor.lattice
        self.get_logger().info(
            f"reconstructing with cameras {', '.join(cameras)} on a {lattice.voxel_size * 1e3:.1f} mm "
            f"lattice of {lattice.shape[0]}x{lattice.shape[1]}x{lattice.shape[2]} voxels from "
            f"{[round(float(v), 3) for v in lattice.origin]} m")
        for message in self.reconstructor.notes:
            self.get_logger().warning(message)
        return self.reconstructor


def main(args: list[str] | None = None) -> int:
    return main_for(NAME, ReconstructionConfig, ReconstructionNode, SUMMARY, args)


if __name__ == "__main__":
    raise SystemExit(main())
