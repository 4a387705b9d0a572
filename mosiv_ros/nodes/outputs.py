"""The nodes' result messages built from core data: estimates, predicted paths and markers.

diagnostic_msgs/DiagnosticArray <-> ``identify.estimates`` statuses, nav_msgs/Path of a predicted
centroid path, visualization_msgs/MarkerArray of the predicted paths and final positions. These
messages exist only on the live graph (never in bags), so they are built with the rclpy classes,
whose constructors default every field not given. Point clouds, images and TF use the shared
conversions of ``mosiv_ros.io.messages`` instead.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Vector3
from nav_msgs.msg import Path
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from mosiv_ros.identify.estimates import LEVELS, Status

PALETTE = ((0.9, 0.2, 0.15), (0.2, 0.7, 0.25), (0.2, 0.4, 0.9), (0.9, 0.7, 0.1), (0.6, 0.3, 0.8))


def stamp(ns: int) -> Time:
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def diagnostics_msg(statuses: Sequence[Status], stamp_ns: int) -> DiagnosticArray:
    return DiagnosticArray(
        header=Header(stamp=stamp(stamp_ns), frame_id=""),
        status=[DiagnosticStatus(level=bytes([LEVELS.index(level)]), name=name, message=message,
                                 hardware_id=hardware_id,
                                 values=[KeyValue(key=k, value=v) for k, v in pairs])
                for name, hardware_id, level, message, pairs in statuses])


def statuses_of(msg: DiagnosticArray) -> list[Status]:
    """ValueError on a status level that is not OK, WARN or ERROR."""
    out = []
    for status in msg.status:
        level = status.level[0] if isinstance(status.level, bytes | bytearray) else int(status.level)
        if level >= len(LEVELS):
            raise ValueError(f"status {status.name!r}: level {level} is not OK/WARN/ERROR")
        out.append((status.name, status.hardware_id, LEVELS[level], status.message,
                    [(kv.key, kv.value) for kv in status.values]))
    return out


def path_msg(stamps_ns: Sequence[int], positions: np.ndarray, frame_id: str = "world") -> Path:
    """A path of positions (F, 3) at absolute stamps, identity orientation."""
    return Path(
        header=Header(stamp=stamp(stamps_ns[0] if len(stamps_ns) else 0), frame_id=frame_id),
        poses=[PoseStamped(header=Header(stamp=stamp(ns), frame_id=frame_id),
                           pose=Pose(position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                                     orientation=Quaternion(w=1.0)))
               for ns, p in zip(stamps_ns, positions, strict=True)])


def markers_msg(names: Sequence[str], paths: np.ndarray, stamp_ns: int,
                frame_id: str = "world") -> MarkerArray:
    """Per object a line strip of its predicted path and a sphere at its last position.

    ``paths`` (F, K, 3). Marker ids 2k and 2k + 1, namespace ``mosiv/<name>``.
    """
    header = Header(stamp=stamp(stamp_ns), frame_id=frame_id)
    markers = []
    for k, name in enumerate(names):
        r, g, b = PALETTE[k % len(PALETTE)]
        colour = ColorRGBA(r=r, g=g, b=b, a=1.0)
        points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in paths[:, k]]
        markers.append(Marker(header=header, ns=f"mosiv/{name}", id=2 * k, type=Marker.LINE_STRIP,
                              action=Marker.ADD, pose=Pose(orientation=Quaternion(w=1.0)),
                              scale=Vector3(x=0.005), color=colour, points=points))
        last = points[-1] if points else Point()
        markers.append(Marker(header=header, ns=f"mosiv/{name}", id=2 * k + 1, type=Marker.SPHERE,
                              action=Marker.ADD, pose=Pose(position=last, orientation=Quaternion(w=1.0)),
                              scale=Vector3(x=0.03, y=0.03, z=0.03), color=colour))
    return MarkerArray(markers=markers)
