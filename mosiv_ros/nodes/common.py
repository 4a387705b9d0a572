"""What every mosiv_ros node shares: QoS profiles, parameters from a stage config, ``main``.

Not for algorithms: a node hands each message to the ROS-free core and publishes what comes back.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from tf2_msgs.msg import TFMessage

from mosiv_ros.config import build, check, describe, parameters, value_of
from mosiv_ros.io.bag import GRIPPER_POSE_TOPIC
from mosiv_ros.io.errors import MosivIOError
from mosiv_ros.io.messages import pointcloud_from_msg, pose_stamped_from_msg, transform_from_msg
from mosiv_ros.io.transforms import PoseStream, StaticTransforms
from mosiv_ros.lifting.lift import LiftedParticles

#: Results a late subscriber must still get (DESIGN.md: reliable + transient_local, depth 1).
LATCHED_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
#: Camera streams (DESIGN.md: the sensor-data profile).
SENSOR_QOS = qos_profile_sensor_data


def sensor_qos(depth: int) -> QoSProfile:
    """The sensor-data profile (best effort, volatile) keeping the last ``depth`` messages.

    A subscriber's own history: it matches any publisher of the profile, and holds ``depth``
    messages while its node is too busy to take them (keep last 5 loses a frame to a 0.2 s stall
    at 30 fps).
    """
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=SENSOR_QOS.reliability,
                      durability=SENSOR_QOS.durability)


#: Per-frame pipeline streams: every frame matters to the next stage, also to a stage that
#: starts late (identify_node needs the whole window): reliable, and transient_local with the
#: last STREAM_HISTORY messages (30 s at 30 fps) kept for late subscribers.
STREAM_HISTORY = 1000
STREAM_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=STREAM_HISTORY,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

#: /tf_static: reliable, transient_local (its publishers latch it), any number of transforms.
TF_STATIC_QOS = QoSProfile(
    depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)

_PARAMETER_TYPES = {
    bool: Parameter.Type.BOOL,
    int: Parameter.Type.INTEGER,
    float: Parameter.Type.DOUBLE,
    str: Parameter.Type.STRING,
    list[str]: Parameter.Type.STRING_ARRAY,
    list[int]: Parameter.Type.INTEGER_ARRAY,
    list[float]: Parameter.Type.DOUBLE_ARRAY,
}


def declare_config(node: Node, config_type: type,
                   check_change: Callable[[Any, dict[str, Any]], None] | None = None) -> Any:
    """Declare one parameter per parameter of a stage config and return the config they give.

    A group's parameters are declared with dotted names (``search.samples``), which a params
    file may nest. Each parameter is declared with its range (``config.value_range``); a value
    outside it stops the node (ValueError). At run time a change is refused, with the reason,
    unless every changed parameter is one the config marks ``run_time``, the config it gives
    passes ``config.check`` and ``check_change(new config, changed values)`` (the node's own
    checks) raises no ValueError.
    """
    values, defaults = {}, config_type()
    for name, f, hint in parameters(config_type):
        default = value_of(defaults, name)
        kind = _PARAMETER_TYPES[hint]
        descriptor = ParameterDescriptor(description=f.metadata.get("help", ""), type=kind.value)
        bounds = f.metadata.get("range")
        if bounds is not None and kind == Parameter.Type.INTEGER:
            descriptor.integer_range = [IntegerRange(from_value=bounds[0], to_value=bounds[1])]
        elif bounds is not None and kind == Parameter.Type.DOUBLE:
            descriptor.floating_point_range = [FloatingPointRange(from_value=bounds[0], to_value=bounds[1])]
        # An empty list default would be typed BYTE_ARRAY by rclpy; declare such a parameter by
        # its type instead. It (and an empty list in a params file) then reads as unset: the default.
        try:
            value = node.declare_parameter(name, default if default != [] else kind, descriptor).value
        except InvalidParameterValueException as error:  # out of its range
            raise ValueError(str(error)) from None
        values[name] = default if value is None else value
    config = check(build(config_type, values))
    node.add_on_set_parameters_callback(partial(_on_set, node, config_type, check_change))
    return config


def _on_set(node: Node, config_type: type, check_change: Callable[[Any, dict[str, Any]], None] | None,
            params: list[Parameter]) -> SetParametersResult:
    """``declare_config``'s check of a run-time parameter change."""
    fields = {name: f for name, f, _ in parameters(config_type)}
    changed = {p.name: p.value for p in params if p.name in fields}  # rclpy's own (use_sim_time) pass
    fixed = sorted(name for name in changed if not fields[name].metadata.get("run_time"))
    if fixed:
        return SetParametersResult(successful=False, reason=f"{', '.join(fixed)}: read at start only")
    current = {name: node.get_parameter(name).value for name in fields}
    try:
        config = check(build(config_type, {name: default if current[name] is None else current[name]
                                           for name, default, _ in describe(config_type)} | changed))
        if check_change is not None:
            check_change(config, changed)
    except ValueError as error:
        return SetParametersResult(successful=False, reason=str(error))
    return SetParametersResult(successful=True)


def print_help(node_name: str, config_type: type, summary: str) -> None:
    """The text ``<node> --help`` prints: what the node does and its parameters."""
    print(f"{node_name}: {summary}\n")
    print(f"usage: ros2 run mosiv_ros {node_name} [--ros-args -p NAME:=VALUE | --params-file FILE]\n")
    print("parameters:")
    for name, default, help_text in describe(config_type):
        print(f"  {name} (default {default!r})\n      {help_text}")


class CoreLogHandler(logging.Handler):
    """Records of the core's Python loggers (``mosiv_ros.*``) on a node's ROS logger."""

    def __init__(self, node_name: str) -> None:
        super().__init__()
        self.ros_logger = rclpy.logging.get_logger(node_name)
        self.setFormatter(logging.Formatter("%(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = f"{record.name.removeprefix('mosiv_ros.')}: {self.format(record)}"
            if record.levelno >= logging.ERROR:
                self.ros_logger.error(text)
            elif record.levelno >= logging.WARNING:
                self.ros_logger.warning(text)
            elif record.levelno >= logging.INFO:
                self.ros_logger.info(text)
            else:
                self.ros_logger.debug(text)
        except Exception:  # a log line must never stop the node
            self.handleError(record)


class _Stopped(BaseException):
    """SIGINT or SIGTERM while the node spins: ends the callback running.

    Not an Exception: no ``except Exception`` in the callback may swallow it.
    """


def main_for(
    node_name: str,
    config_type: type,
    factory: Callable[[], Node],
    summary: str,
    args: Sequence[str] | None = None,
) -> int:
    """Run a node until Ctrl-C or shutdown: the ``main`` of every mosiv_ros executable."""
    argv = list(sys.argv if args is None else args)
    user_args = argv[1 : argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if "-h" in user_args or "--help" in user_args:
        print_help(node_name, config_type, summary)
        return 0
    # rclpy's own handler (SIGINT, SIGTERM) shuts the context down, and spin then raises
    # ExternalShutdownException, but only once the callback running returns: a lift or a
    # rollout may take minutes. rclpy chains to Python's handler, which ends that callback at
    # once (_Stopped), only while spinning: Python's default would raise KeyboardInterrupt at
    # whatever line runs next, the clean-up below included, and SIGTERM's would kill the node.
    spinning = threading.Event()

    def stop(_signum: int, _frame: object) -> None:
        if spinning.is_set():
            spinning.clear()  # once: the clean-up that follows runs to its end
            raise _Stopped

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, stop)
    rclpy.init(args=argv)
    core = logging.getLogger("mosiv_ros")  # the core's log lines go to the node's log
    handler = CoreLogHandler(node_name)
    core.setLevel(int(handler.ros_logger.get_effective_level()))  # rcutils uses Python's levels
    core.propagate = False
    core.addHandler(handler)
    node = None
    try:
        # The executor exists before "ready" is logged: a Ctrl-C right after that line must find
        # everything in place (creating an executor on a context already shut down fails).
        executor = SingleThreadedExecutor()
        node = factory()
        executor.add_node(node)
        node.get_logger().info(f"{node_name} ready")
        done = getattr(node, "done", None)
        spinning.set()
        try:
            if done is None:
                executor.spin()
            else:
                executor.spin_until_future_complete(done)
        finally:
            spinning.clear()
    except (ExternalShutdownException, _Stopped):
        pass
    except Exception as error:
        if not rclpy.ok():
            pass  # stopped while starting: Ctrl-C shut the context down under the constructor
        elif isinstance(error, (MosivIOError, ValueError)):
            # Bad settings or input found while starting: one clear line, no traceback.
            print(f"{node_name}: error: {error}", file=sys.stderr)
            return 2
        else:
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    finished = getattr(node, "done", None)
    return 1 if finished is not None and finished.done() and finished.result() is False else 0


def guarded(
    node: Node, topic: str, convert: Callable[[Any], Any], handle: Callable[[Any], None]
) -> Callable[[Any], None]:
    """A subscription callback: convert the message with the core, hand the result on.

    A malformed message is logged with the topic and the problem and dropped; the node keeps
    running.
    """

    def callback(msg: Any) -> None:
        try:
            value = convert(msg)
        except (MosivIOError, ValueError) as error:
            node.get_logger().error(f"{topic}: dropped malformed message: {error}")
            return
        handle(value)

    return callback


def lifted_from_msg(msg: Any) -> LiftedParticles:
    """A ``/mosiv/particles`` cloud as lifted particles (ValueError if it lacks their fields)."""
    return LiftedParticles.from_cloud(pointcloud_from_msg(msg))


def log_cloud(node: Node, topic: str, cloud: Any) -> None:
    """Log one line on a received point cloud: stamp, points, points per object."""
    ids, counts = np.unique(cloud.object_id, return_counts=True)
    objects = ", ".join(f"{i} ({n} pts)" for i, n in zip(ids.tolist(), counts.tolist(), strict=True)) or "none"
    node.get_logger().info(
        f"{topic}: stamp {cloud.stamp_ns} ns, {len(cloud.xyz)} points, objects {objects}"
    )


def gripper_poses(node: Node, on_change: Callable[[], None] | None = None,
                  transforms: StaticTransforms | None = None) -> PoseStream:
    """Subscribe ``node`` to ``/gripper/pose`` and ``/tf_static``; the poses as they arrive.

    The poses keep their frames until asked for in the world (``PoseStream.world``), so either
    topic may come first; ``on_change`` is called after each pose or transform message. A node
    that keeps ``/tf_static`` itself passes its ``transforms`` (no second subscription). A
    malformed message is logged and dropped (``guarded``).
    """
    stream = PoseStream(transforms if transforms is not None else StaticTransforms())

    def on_transforms(transforms: list) -> None:
        for parent, child, T in transforms:
            stream.transforms.add(parent, child, T)
        if on_change is not None:
            on_change()

    def on_pose(pose: tuple) -> None:
        stream.add(pose[0], pose[2], pose[1])
        if on_change is not None:
            on_change()

    if transforms is None:
        node.create_subscription(
            TFMessage, "/tf_static",
            guarded(node, "/tf_static", lambda msg: [transform_from_msg(t) for t in msg.transforms],
                    on_transforms), TF_STATIC_QOS)
    node.create_subscription(
        PoseStamped, GRIPPER_POSE_TOPIC,
        guarded(node, GRIPPER_POSE_TOPIC,
                lambda msg: (*pose_stamped_from_msg(msg), str(msg.header.frame_id)),
                on_pose), STREAM_QOS)
    return stream


def world_gripper_poses(node: Node, stream: PoseStream) -> list:
    """The gripper's poses in the world so far (their number logged); a frame no transform reaches too."""
    poses, unreached = stream.world()
    if poses:
        node.get_logger().info(f"{GRIPPER_POSE_TOPIC}: {len(poses)} gripper poses in the world")
    if unreached:
        node.get_logger().warning(
            f"{GRIPPER_POSE_TOPIC}: poses in frame(s) {unreached} left out: no chain of /tf_static "
            "transforms from world reaches them")
    return poses
