"""Assembly of one camera's frames from its separate topics, message by message.

A camera publishes RGB, instance mask, optional depth and CameraInfo on separate topics with the
same header stamp. ``CameraFrameAssembler`` pairs them by exact stamp, checks that their
sizes agree with each other and with the CameraInfo, and marks unusable depth as missing. The
bag reader and ``reconstruction_node`` both use it, so a recording read from disk and one
received live are assembled by one rule.

Not for matching frames *across* cameras (stamps differ there): see ``recording.FrameMatcher``.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from mosiv_ros.io.errors import MessageError
from mosiv_ros.io.recording import CameraIntrinsics, Frame

LOG = logging.getLogger(__name__)

KINDS = ("rgb", "mask", "depth")
UNUSABLE_DEPTH_WARNING = 0.5
"""Fraction of a frame's object pixels without a usable depth at which a camera is reported."""


def usable_depth(depth: np.ndarray) -> np.ndarray:
    """``depth`` with every non-finite or non-positive value made NaN: no return (DESIGN.md).

    +inf would otherwise claim empty space all along its ray and carve objects away; 0 and
    negative values would put surface points at or behind the camera.
    """
    with np.errstate(invalid="ignore"):
        usable = np.isfinite(depth) & (depth > 0)
    return depth if usable.all() else np.where(usable, depth, np.float32(np.nan))


def check_frame(camera: str, frame: Frame, intrinsics: CameraIntrinsics | None) -> None:
    """Raise MessageError if a frame's images disagree in size or type with each other or K."""
    where = f"camera '{camera}' stamp {frame.stamp_ns} ns"
    if frame.rgb.ndim != 3 or frame.rgb.shape[2] != 3 or frame.rgb.dtype != np.uint8:
        raise MessageError(f"{where}: color image must be rgb8 (HxWx3 uint8), got "
                           f"{frame.rgb.dtype} {frame.rgb.shape}")
    if frame.mask.ndim != 2 or frame.mask.dtype not in (np.uint8, np.uint16):
        raise MessageError(f"{where}: instance mask must be mono8 or mono16, got "
                           f"{frame.mask.dtype} {frame.mask.shape}")
    size = frame.rgb.shape[:2]
    if frame.mask.shape != size:
        raise MessageError(f"{where}: instance mask is {frame.mask.shape[1]}x{frame.mask.shape[0]}"
                           f" but the color image is {size[1]}x{size[0]}")
    if frame.depth is not None:
        if frame.depth.dtype != np.float32 or frame.depth.shape != size:
            raise MessageError(f"{where}: depth must be 32FC1 of the color image's size "
                               f"{size[1]}x{size[0]}, got {frame.depth.dtype} "
                               f"{frame.depth.shape[1::-1]}")
    if intrinsics is not None and (intrinsics.height, intrinsics.width) != size:
        raise MessageError(f"{where}: images are {size[1]}x{size[0]} but CameraInfo says "
                           f"{intrinsics.width}x{intrinsics.height}")


def mask_pixel_counts(frames: Iterable[Frame]) -> dict[int, int]:
    """Pixels of each object id (background 0 left out) over the masks of several frames."""
    counts: dict[int, int] = {}
    for frame in frames:
        ids, n = np.unique(frame.mask[frame.mask > 0], return_counts=True)
        for i, c in zip(ids.tolist(), n.tolist(), strict=True):
            counts[i] = counts.get(i, 0) + c
    return counts


@dataclass
class CameraFrameAssembler:
    """Collects one camera's images by stamp and returns each frame once it is complete.

    A frame is complete when its RGB image and mask have arrived, and its depth too when
    ``expect_depth`` is set. At most ``max_pending`` incomplete stamps are kept; older ones are
    dropped and counted in ``dropped`` (a lost message must not hold memory forever). A complete
    frame's depth is ``usable_depth``; the first frame whose object pixels mostly lack one is
    logged as a warning (``depth_reported``).
    """

    camera: str
    expect_depth: bool = False
    max_pending: int = 30
    intrinsics: CameraIntrinsics | None = None
    dropped: int = 0
    depth_reported: bool = False
    _pending: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)

    def add(self, kind: str, stamp_ns: int, image: np.ndarray) -> Frame | None:
        """Add one image ('rgb', 'mask' or 'depth'); return the frame it completes, if any."""
        if kind not in KINDS:
            raise ValueError(f"unknown image kind {kind!r}, expected one of {KINDS}")
        parts = self._pending.setdefault(stamp_ns, {})
        parts[kind] = image
        needed = ("rgb", "mask", "depth") if self.expect_depth else ("rgb", "mask")
        if not all(k in parts for k in needed):
            self._evict()
            return None
        del self._pending[stamp_ns]
        frame = Frame(stamp_ns=stamp_ns, rgb=parts["rgb"], mask=parts["mask"],
                      depth=parts.get("depth"))
        check_frame(self.camera, frame, self.intrinsics)
        if frame.depth is not None:
            frame.depth = usable_depth(frame.depth)
            self._report_depth(frame)
        return frame

    def _report_depth(self, frame: Frame) -> None:
        """Warn, once, when a frame's object pixels mostly have no usable depth."""
        objects = frame.mask > 0
        if self.depth_reported or not objects.any():
            return
        missing = float(np.mean(np.isnan(frame.depth[objects])))
        if missing >= UNUSABLE_DEPTH_WARNING:
            self.depth_reported = True
            LOG.warning("camera '%s': no usable depth at %.0f%% of its object pixels at stamp %d ns "
                        "(NaN, infinite, zero or negative values count as no return: they neither "
                        "carve nor give surface points; reported once per camera)", self.camera,
                        100 * missing, frame.stamp_ns)

    def _evict(self) -> None:
        while len(self._pending) > self.max_pending:
            oldest = min(self._pending)
            del self._pending[oldest]
            self.dropped += 1
            LOG.warning("camera '%s': dropped incomplete frame at stamp %d ns", self.camera, oldest)

    @property
    def pending(self) -> int:
        """Stamps waiting for a missing image."""
        return len(self._pending)
