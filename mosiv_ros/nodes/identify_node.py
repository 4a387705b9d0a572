"""identify_node: observed geometry and particles in, per-object material estimates out (stage 3).

Subscribes to ``/mosiv/observed_objects`` (one cloud per frame set), ``/gripper/pose`` with
``/tf_static`` (a declared gripper's trajectory, placed in the world: the fit's collider),
``/mosiv/surface_tracks``
(the surface tracks alive at each frame set, kept by stamp and joined to the frame set of the
same stamp: the fit's track loss) and ``/mosiv/particles`` (latched). Once it has the particles
and ``window`` frames from the particles' frame on (with ``window`` 0: at least two frames and
``idle_timeout`` seconds without a new one; with a window that the stream never fills: three
times that), and, while a node publishes surface tracks, once each of those frames has its tracks
or no track cloud came for ``idle_timeout`` seconds (tracks and frame sets travel on two topics,
so either may arrive first; a lost track cloud delays the fit by at most three times that), and,
for a scene that declares a gripper, once its poses reach the window's last stamp (at most three
times ``idle_timeout`` after the window is complete: a late DDS match, or a stream without them), it
runs the core's ``identify_objects`` in a worker thread (an object whose family
the scene leaves out gets one of ``families``, chosen by held-out error first), reporting
progress on ``/diagnostics`` and in its log, then publishes ``/mosiv/material_estimates``
(diagnostic_msgs/DiagnosticArray, latched: one status per object named ``mosiv/<object>`` with
hardware_id the object id, plus ``mosiv/scene``) and writes the estimates to ``output_yaml``
(which prediction_node also reads; written whole or not at all, and checked writable when the
node starts, as ``close_loop_dir`` is). A failed fit is published as ERROR statuses saying why;
so is an unexpected error in the worker (also an ERROR status on ``/diagnostics``, and logged
with its traceback). An empty particle cloud is logged and the node waits for a usable one; a
malformed cloud on any topic is logged and dropped; a frame set the stream lost is a gap the fit
simulates through. On the topic graph the fit uses the 3D losses only (Chamfer and surface
tracks): the silhouettes stay with the reconstruction (``mosiv run`` uses them too).

With ``close_loop`` it then closes the loop on the same frames (``mosiv_ros.loop``: the last
30 % of the window held out to judge candidate effects) and writes the report, the closed
model's estimates and its scene declaration (``closed_scene.yaml``, a ``scene`` parameter for
prediction_node) into ``close_loop_dir``.
"""

from __future__ import annotations

import threading
import time
import traceback
from dataclasses import replace

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from mosiv_ros.config import IdentifyConfig
from mosiv_ros.identify.estimates import ERROR
from mosiv_ros.identify.family import candidate_families
from mosiv_ros.identify.run import UNITS, build_kernels_aside, failed_estimates, identify_objects
from mosiv_ros.io.bag import load_scene
from mosiv_ros.io.files import OutputDir, check_output_file
from mosiv_ros.io.messages import pointcloud_from_msg
from mosiv_ros.io.scene import Scene
from mosiv_ros.lifting.lift import LiftedParticles
from mosiv_ros.loop.closure import LoopClosure, LoopError
from mosiv_ros.loop.report import write_loop_report
from mosiv_ros.nodes.common import (
    LATCHED_QOS,
    STREAM_QOS,
    declare_config,
    gripper_poses,
    guarded,
    lifted_from_msg,
    main_for,
    world_gripper_poses,
)
from mosiv_ros.nodes.outputs import diagnostics_msg
from mosiv_ros.nodes.reconstruction_node import TRACKS_TOPIC
from mosiv_ros.progress import TimeLeft, duration
from mosiv_ros.recon.reconstruct import ObservedFrame
from mosiv_ros.recon.tracks import TrackPoints
from mosiv_ros.sim.errors import SimulationError
from mosiv_ros.sim.runtime import resolve_device

NAME = "identify_node"
SUMMARY = "fit per-object material parameters with the differentiable MPM simulator"


class IdentifyNode(Node):
    """Thin shell: gathers the window, runs the core's identification, publishes estimates."""

    def __init__(self) -> None:
        super().__init__(NAME)
        self.config: IdentifyConfig = declare_config(self, IdentifyConfig)
        candidate_families(self.config.families)  # a bad list stops the node now, not after the stream
        resolve_device(self.config.device)  # a device that is not there stops the node now
        build_kernels_aside(self.config.device)  # while the recording arrives
        self.scene: Scene = load_scene(self.config.scene) if self.config.scene else Scene()
        # outputs that cannot be written stop the node now, not after the fit
        if self.config.output_yaml:
            check_output_file(self.config.output_yaml)
        self.loop_dir = OutputDir(self.config.close_loop_dir, f"{NAME} loop closure") \
            if self.config.close_loop else None
        self.estimates_pub = self.create_publisher(
            DiagnosticArray, "/mosiv/material_estimates", LATCHED_QOS)
        self.progress_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.frames: dict[int, ObservedFrame] = {}
        self.tracks: dict[int, TrackPoints] = {}
        self.particles: LiftedParticles | None = None
        self.last_frame = time.monotonic()
        self.last_tracks = 0.0
        self.ready = 0.0  # when the window was first complete (or the stream first quiet)
        self.worker: threading.Thread | None = None
        self.published = False  # estimates of the fit are on /mosiv/material_estimates
        self.create_subscription(
            PointCloud2, "/mosiv/observed_objects",
            guarded(self, "/mosiv/observed_objects",
                    lambda msg: ObservedFrame.from_cloud(pointcloud_from_msg(msg)), self._on_observed), STREAM_QOS)
        self.create_subscription(
            PointCloud2, TRACKS_TOPIC,
            guarded(self, TRACKS_TOPIC, lambda msg: TrackPoints.from_cloud(pointcloud_from_msg(msg)),
                    self._on_tracks), STREAM_QOS)
        self.create_subscription(
            PointCloud2, "/mosiv/particles",
            guarded(self, "/mosiv/particles", lifted_from_msg, self._on_particles), LATCHED_QOS)
        self.gripper = gripper_poses(self)
        self.create_timer(0.5, self._maybe_start)
        if self.config.loss.silhouette_weight > 0:
            self.get_logger().info("the topic graph carries no silhouettes: fitting the 3D loss")

    def _on_observed(self, frame: ObservedFrame) -> None:
        if self.worker is not None:
            return
        self.frames[frame.stamp_ns] = frame
        self.last_frame = time.monotonic()

    def _on_tracks(self, tracks: TrackPoints) -> None:
        if self.worker is None:
            self.tracks[tracks.stamp_ns] = tracks
            self.last_tracks = time.monotonic()

    def _on_particles(self, particles: LiftedParticles) -> None:
        self.particles = particles
        self.get_logger().info(f"/mosiv/particles: {self.particles.summary()}")

    def _window(self) -> list[ObservedFrame]:
        start = self.particles.stamp_ns if self.particles is not None else 0
        return [replace(f, tracks=self.tracks.get(stamp)) for stamp, f in sorted(self.frames.items())
                if stamp >= start]

    def _maybe_start(self) -> None:
        if self.worker is not None or self.particles is None:
            return
        frames = self._window()
        now = time.monotonic()
        window, idle = self.config.window, self.config.idle_timeout
        if window and len(frames) >= window:
            frames, short = frames[:window], False
        elif len(frames) < 2 or now - self.last_frame <= idle * (3 if window else 1):
            return  # with a window: wait for it unless the stream has clearly ended
        else:
            short = bool(window)
        tracked = sum(f.tracks is not None for f in frames)
        self.ready = self.ready or now
        if (tracked < len(frames) and self.count_publishers(TRACKS_TOPIC) and now - self.ready <= 3 * idle
                and now - max(self.ready, self.last_tracks) <= idle):
            return  # the window's tracks may still be on their way
        if self.scene.gripper is not None and now - self.ready <= 3 * idle:
            poses = self.gripper.world()[0]
            if not poses or poses[-1][0] < frames[-1].stamp_ns:
                return  # the gripper's poses over the window may still be on their way
        if short:
            self.get_logger().warning(f"the stream went quiet after {len(frames)} of the {window} "
                                      "frames of the window; fitting those")
        self.get_logger().info(f"fitting {len(frames)} frames from stamp {frames[0].stamp_ns} ns "
                               f"({tracked} with surface tracks)")
        self.worker = threading.Thread(target=self._fit, args=(frames,), daemon=True)
        self.worker.start()

    def _fit(self, frames: list[ObservedFrame]) -> None:
        """The worker thread: the fit, then the loop closure; an unexpected error is reported.

        Logged with its traceback and published as an ERROR status on ``/diagnostics`` (and as
        ERROR estimates when none were published yet): the thread must not die silently.
        """
        try:
            self._identify(frames)
        except Exception as error:
            reason = f"unexpected {type(error).__name__}: {error}"
            self.get_logger().error(f"identification failed: {reason}\n{traceback.format_exc()}")
            stamp_ns = self.get_clock().now().nanoseconds
            self.progress_pub.publish(diagnostics_msg(
                [("mosiv/identify", "", ERROR, f"identification failed: {reason}", [])], stamp_ns))
            if not self.published:
                estimates = failed_estimates(self.particles, self.scene, reason, frames)
                self.estimates_pub.publish(diagnostics_msg(estimates.statuses(), estimates.stamp_ns))

    def _identify(self, frames: list[ObservedFrame]) -> None:
        started = time.monotonic()
        time_left = TimeLeft()

        def progress(record: dict) -> None:
            phase, done, total = record["phase"], record["done"], record["total"]
            candidate = record.get("candidate")  # a candidate family's fit (identify.family)
            label = f"family candidate {candidate}: {phase}" if candidate else phase
            left = time_left(label, done, total)
            pairs = [("phase", phase), ("done", str(done)), ("total", str(total)),
                     ("time_left_s", "unknown" if left is None else f"{left:.0f}"),
                     ("elapsed_s", f"{time.monotonic() - started:.1f}")]
            text = f"{label}: {done}/{total} {UNITS[phase]}s"
            if phase == "fit":
                pairs += [("stage", str(record["stage"])), ("window", str(record["window"])),
                          ("iteration", str(record["iteration"])), ("loss", f"{record['loss']:.6g}")]
                text += f" (stage {record['stage']}, window {record['window']}): loss {record['loss']:.4g}"
            if candidate:
                pairs.append(("candidate", candidate))
            self.progress_pub.publish(diagnostics_msg(
                [("mosiv/identify", "", "OK", f"identifying: {label}", pairs)],
                self.get_clock().now().nanoseconds))
            self.get_logger().info(f"{text}; time left in this phase {duration(left)}")

        poses = world_gripper_poses(self, self.gripper)  # the fit's and the loop closure's
        identification = identify_objects(frames, self.particles, self.scene, self.config,
                                          gripper_poses=poses, progress=progress)
        estimates = identification.estimates
        self.estimates_pub.publish(diagnostics_msg(estimates.statuses(), estimates.stamp_ns))
        self.published = True
        if self.config.output_yaml:
            path = estimates.write(self.config.output_yaml)
            self.get_logger().info(f"estimates written to {path} (prediction_node --ros-args "
                                   f"--params-file {path})")
        for obj in estimates.objects:
            values = ", ".join(f"{k}={v:.4g}" for k, v in obj.params.items())
            self.get_logger().info(f"estimate {obj.name} ({obj.family}) {obj.level}: {values}")
        self.get_logger().info(f"identification done in {time.monotonic() - started:.1f} s")
        if self.config.close_loop:
            self._close_loop(frames, poses)

    def _close_loop(self, frames: list[ObservedFrame], poses: list) -> None:
        started = time.monotonic()

        time_left = TimeLeft()

        def progress(phase: str, done: int, total: int, unit: str) -> None:
            left = duration(time_left(phase, done, total))
            self.get_logger().info(f"loop closure: {phase} {done}/{total} {unit}s; time left in "
                                   f"this phase {left}")

        try:
            result = LoopClosure(frames, self.particles, self.scene, self.config,
                                 gripper_poses=poses,
                                 progress=progress).run()
        except (LoopError, SimulationError, ValueError) as error:
            self.get_logger().error(f"loop closure failed: {error}")
            return
        write_loop_report(self.loop_dir, result)  # the core logged the verdict
        self.get_logger().info(f"loop closure report written to {self.config.close_loop_dir} "
                               f"({time.monotonic() - started:.1f} s)")


def main(args: list[str] | None = None) -> int:
    return main_for(NAME, IdentifyConfig, IdentifyNode, SUMMARY, args)


if __name__ == "__main__":
    raise SystemExit(main())
