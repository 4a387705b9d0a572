"""In-memory, typed data of a multi-camera recording, and frame matching across cameras.

What it is for: the dataclasses every stage passes around (intrinsics, frames, cameras, a whole
recording, point clouds) and the one implementation of cross-camera frame matching, usable on a
finished recording (``match_frames``) and on a live stream (``FrameMatcher``).
What it is not for: reading or writing bags (``mosiv_ros.io.bag``) or messages
(``mosiv_ros.io.messages``).

Arrays follow DESIGN.md: rgb (H, W, 3) uint8, mask (H, W) uint8/uint16 object ids (0 =
background), depth (H, W) float32 metres along the optical z axis (NaN = no return), poses 4x4
float64 homogeneous transforms, stamps int nanoseconds.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosiv_ros.io.scene import Scene

_LOG = logging.getLogger(__name__)

DEFAULT_TOLERANCE_NS = 5_000_000
"""Default cross-camera matching tolerance: 5 ms (a quarter period of a 50 Hz camera)."""
DEFAULT_HORIZON_NS = 1_000_000_000
"""Default age (1 s behind the newest stamp) after which a streaming partial set is dropped."""


def _check_pose(name: str, T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{name}: expected a 4x4 matrix, got shape {T.shape}")
    return T


@dataclass
class CameraIntrinsics:
    """Pinhole calibration of one camera, as in sensor_msgs/CameraInfo.

    ``K`` is the 3x3 camera matrix (pixels), ``D`` the distortion coefficients of
    ``distortion_model`` (for plumb_bob: k1, k2, p1, p2, k3). Pixel centres are at integer
    coordinates (OpenCV/ROS convention). Construction checks the calibration: positive, finite
    focal lengths, the principal point inside the image, every value finite (ValueError naming
    the CameraInfo field, e.g. ``k[0] (fx)``).
    """

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))
    distortion_model: str = "plumb_bob"

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64)
        self.D = np.asarray(self.D, dtype=np.float64).ravel()
        if self.K.shape != (3, 3):
            raise ValueError(f"K: expected a 3x3 matrix, got shape {self.K.shape}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        self._check_calibration()

    def _check_calibration(self) -> None:
        """ValueError naming the CameraInfo field (``k[i]``, ``d[i]``) of an unusable calibration."""
        K = self.K.ravel()
        for index, name in ((0, "fx"), (4, "fy")):
            if not (math.isfinite(K[index]) and K[index] > 0):
                raise ValueError(f"k[{index}] ({name}) must be a positive, finite number of pixels, "
                                 f"got {K[index]}")
        for index, name, size in ((2, "cx", self.width), (5, "cy", self.height)):
            if not -0.5 <= K[index] <= size - 0.5:  # False for NaN too
                raise ValueError(f"k[{index}] ({name}) = {K[index]}: the principal point must lie inside "
                                 f"the {self.width}x{self.height} image ({name} in -0.5 .. {size - 0.5})")
        for index, value in enumerate(K):
            if not math.isfinite(value):
                raise ValueError(f"k[{index}] must be finite, got {value}")
        for index, value in enumerate(self.D):
            if not math.isfinite(value):
                raise ValueError(f"d[{index}] (distortion) must be finite, got {value}")

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of points (N, 3) given in the optical frame, in metres.

        Points at or behind the image plane (z <= 0) project to NaN. Distortion is applied for
        plumb_bob; any other model must have all-zero coefficients.
        """
        points = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(points[:, 2] > 0, points[:, 2], np.nan)
            x, y = points[:, 0] / z, points[:, 1] / z
        if np.any(self.D):
            if self.distortion_model != "plumb_bob":
                raise ValueError(f"cannot apply distortion model {self.distortion_model!r}")
            k1, k2, p1, p2, k3 = np.pad(self.D, (0, max(0, 5 - self.D.size)))[:5]
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            x, y = (
                x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
            )
        uvw = np.stack([x, y, np.ones_like(x)], axis=1) @ self.K.T
        return uvw[:, :2] / uvw[:, 2:]


@dataclass
class Frame:
    """One camera's observation at one stamp: colour, instance mask and optional depth.

    Not validated on construction: ``mosiv_ros.io.streams.check_frame`` is the one rule that
    checks a frame's arrays against each other and the calibration.
    """

    stamp_ns: int
    rgb: np.ndarray
    mask: np.ndarray
    depth: np.ndarray | None = None

    @property
    def size(self) -> tuple[int, int]:
        """(height, width) in pixels."""
        return self.rgb.shape[0], self.rgb.shape[1]


@dataclass
class Camera:
    """A calibrated camera and its frames in strictly increasing stamp order.

    ``T_world_optical`` maps points in ``<name>_optical`` (x right, y down, z forward) to world.
    """

    name: str
    intrinsics: CameraIntrinsics
    T_world_optical: np.ndarray
    frames: list[Frame] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.T_world_optical = _check_pose("T_world_optical", self.T_world_optical)
        size = (self.intrinsics.height, self.intrinsics.width)
        for index, frame in enumerate(self.frames):
            if frame.size != size:
                raise ValueError(
                    f"camera {self.name!r}: frames[{index}] is {frame.size}, intrinsics say {size}"
                )
            if index and frame.stamp_ns <= self.frames[index - 1].stamp_ns:
                raise ValueError(f"camera {self.name!r}: frames are not in increasing stamp order")

    @property
    def stamps_ns(self) -> list[int]:
        """Stamps of the frames, in order."""
        return [frame.stamp_ns for frame in self.frames]


@dataclass
class Recording:
    """A whole multi-camera recording: cameras, scene declaration, kinematic gripper poses.

    ``gripper_poses`` holds (stamp_ns, T_world_gripper) pairs in stamp order; ``path`` is the
    bag it was read from, if any.
    """

    cameras: dict[str, Camera]
    scene: Scene = field(default_factory=Scene)
    gripper_poses: list[tuple[int, np.ndarray]] = field(default_factory=list)
    path: Path | None = None


@dataclass
class PointCloud:
    """Points in ``frame_id`` with their object ids and any extra per-point fields.

    ``xyz`` (N, 3) float32 metres, ``object_id`` (N,) uint16, ``fields`` name -> (N,) array
    (e.g. ``t`` float32 seconds after ``stamp_ns``, ``volume`` float32 m^3, ``material`` uint8).
    """

    xyz: np.ndarray
    object_id: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    stamp_ns: int = 0
    frame_id: str = "world"

    def __post_init__(self) -> None:
        self.xyz = np.asarray(self.xyz, dtype=np.float32).reshape(-1, 3)
        self.object_id = np.asarray(self.object_id, dtype=np.uint16).ravel()
        n = len(self.xyz)
        if len(self.object_id) != n:
            raise ValueError(f"object_id: expected {n} values, got {len(self.object_id)}")
        for name, values in self.fields.items():
            if len(values) != n:
                raise ValueError(f"fields[{name!r}]: expected {n} values, got {len(values)}")


@dataclass
class FrameSet:
    """Frames of several cameras taken at (nearly) the same time.

    ``stamp_ns`` is the earliest stamp in the set; every frame lies within the matching tolerance
    of it. A camera absent from ``frames`` contributed no frame to this set.
    """

    stamp_ns: int
    frames: dict[str, Frame]


class FrameMatcher:
    """Incremental cross-camera frame matching, for live streams and finished recordings alike.

    Rules: a frame joins the pending set that keeps the spread of its stamps (newest minus
    earliest) within ``tolerance_ns`` and still lacks that camera; among several it joins the one
    with the smallest resulting spread, otherwise it opens a new set. A set is complete, and
    returned by ``add``, once every camera contributed. When ``horizon_ns`` is not None, a partial
    set whose earliest stamp is more than ``horizon_ns`` behind the newest stamp seen is dropped
    and counted in ``dropped``. ``flush`` hands back the partial sets still pending.
    """

    def __init__(
        self,
        camera_names: Iterable[str],
        tolerance_ns: int = DEFAULT_TOLERANCE_NS,
        horizon_ns: int | None = DEFAULT_HORIZON_NS,
    ) -> None:
        self.camera_names = tuple(camera_names)
        if not self.camera_names or len(set(self.camera_names)) != len(self.camera_names):
            raise ValueError(f"camera_names must be unique and non-empty: {self.camera_names}")
        if tolerance_ns < 0:
            raise ValueError(f"tolerance_ns must be >= 0, got {tolerance_ns}")
        self.tolerance_ns = int(tolerance_ns)
        self.horizon_ns = horizon_ns
        self.dropped = 0
        self._pending: list[dict[str, Frame]] = []
        self._newest_ns: int | None = None

    @property
    def pending(self) -> int:
        """Number of partial sets waiting for more cameras."""
        return len(self._pending)

    def add(self, camera: str, frame: Frame) -> list[FrameSet]:
        """Add one frame of ``camera``; return the sets this completes (zero or one)."""
        if camera not in self.camera_names:
            raise ValueError(f"unknown camera {camera!r} (expected one of {self.camera_names})")
        stamp = frame.stamp_ns
        best: dict[str, Frame] | None = None
        best_spread = 0
        for group in self._pending:
            if camera in group:
                continue
            stamps = [f.stamp_ns for f in group.values()] + [stamp]
            spread = max(stamps) - min(stamps)
            if spread <= self.tolerance_ns and (best is None or spread < best_spread):
                best, best_spread = group, spread
        if best is None:
            best = {}
            self._pending.append(best)
        best[camera] = frame

        complete = []
        if len(best) == len(self.camera_names):
            self._pending.remove(best)
            complete.append(self._to_set(best))
        self._newest_ns = stamp if self._newest_ns is None else max(self._newest_ns, stamp)
        if self.horizon_ns is not None:
            self._drop_older_than(self._newest_ns - self.horizon_ns)
        return complete

    def flush(self, before_ns: int | None = None) -> list[FrameSet]:
        """Return pending partial sets in stamp order and forget them.

        With ``before_ns``, only the sets whose earliest stamp is before it (when frames arrive in
        stamp order, those older than the newest stamp minus the tolerance can no longer grow).
        """
        done = [g for g in self._pending if before_ns is None or _earliest(g) < before_ns]
        self._pending = [g for g in self._pending if not any(g is d for d in done)]
        return sorted((self._to_set(g) for g in done), key=lambda s: s.stamp_ns)

    def _drop_older_than(self, limit_ns: int) -> None:
        keep = []
        for group in self._pending:
            if _earliest(group) < limit_ns:
                self.dropped += 1
                _LOG.debug(
                    "dropping partial frame set of %s, older than %d ns", list(group), limit_ns
                )
            else:
                keep.append(group)
        self._pending = keep

    def _to_set(self, group: dict[str, Frame]) -> FrameSet:
        frames = {name: group[name] for name in self.camera_names if name in group}
        return FrameSet(_earliest(frames), frames)


def _earliest(group: Mapping[str, Frame]) -> int:
    return min(frame.stamp_ns for frame in group.values())


def match_frames(
    cameras: Mapping[str, Camera], tolerance_ns: int = DEFAULT_TOLERANCE_NS
) -> list[FrameSet]:
    """Group the frames of all ``cameras`` into time-ordered sets (see FrameMatcher's rules).

    Frames are fed in stamp order and nothing is dropped: sets where some camera has no frame
    within tolerance are returned too, without that camera, so that callers can decide.
    """
    matcher = FrameMatcher(cameras, tolerance_ns, horizon_ns=None)
    events = [
        (frame.stamp_ns, index, name, frame)
        for index, name in enumerate(cameras)
        for frame in cameras[name].frames
    ]
    sets: list[FrameSet] = []
    for stamp, _, name, frame in sorted(events, key=lambda event: event[:2]):
        sets += matcher.flush(before_ns=stamp - tolerance_ns)
        sets += matcher.add(name, frame)
    sets += matcher.flush()
    return sorted(sets, key=lambda s: s.stamp_ns)
