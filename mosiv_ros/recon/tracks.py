"""Surface tracks: points of each object's surface followed over frames, with ids and confidences.

What it is for: what the texture of an object shows and its silhouette does not (a spinning
ball, a pressed cube whose outline barely moves). ``SurfaceTracker`` runs beside carving in
stage 1 (``Reconstructor``): per camera and per object,

1. seeds: Shi-Tomasi corners of the object's pixels (``cv2.goodFeaturesToTrack``: the relative
   ``quality`` and the spacing ``spacing``, px, of ``config.TrackConfig``) inside its mask shrunk by a pixel,
   wherever no live track of the object is within the spacing; each new track gets a new id;
2. 2D motion: dense DIS optical flow (``cv2.DISOpticalFlow``, at full resolution) of the grey
   image from the last frame to this one and back, on images in which everything outside the object's mask is set to
   the object's mean grey (so that neither the background nor another object drags the flow);
   a track moves by the forward flow at its position, and is kept only if the backward flow
   brings it back to within ``flow_tolerance`` px (the forward-backward check) and it
   still lies on the object (all four pixels around it are the object's);
3. 3D: with a depth image, the point at the bilinear depth around the track (all four pixels
   with a return); without one, where the track's ray first enters the object's carved voxels
   (every camera's silhouette bounds them: the visual hull);
4. confidence: 1 at birth, multiplied at every step by 1 - (e / tolerance)^2 for the step's
   forward-backward error e (px), so it falls as a track's errors add up.

A track that fails a check, leaves the mask, loses its 3D point or whose camera misses a frame
set ends; it is never revived (a new one may start there). Nothing here knows the renderer: the
checks are in pixels of the images themselves.

``TrackPoints`` is one frame set's tracks (the ``/mosiv/surface_tracks`` cloud); ``SurfaceTracks``
the whole recording's, as dense (frames, tracks) arrays from which a loss can attach the tracks
alive at the first fitted frame to the particles there. What it is not for: losses
(``mosiv_ros.identify``) or geometry (``reconstruct``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from mosiv_ros.config import TrackConfig
from mosiv_ros.io.recording import PointCloud
from mosiv_ros.recon.views import View

FLOW_PATCH = 6
"""DIS patch side, pixels (stride a third of it)."""
TRACK_FIELDS = ("track_id", "confidence")
"""``/mosiv/surface_tracks`` fields beyond x, y, z and object_id: uint32 and float32."""


@dataclass
class TrackPoints:
    """The tracks alive at one stamp: world points (M, 3) m, object ids, track ids, confidences."""

    stamp_ns: int
    xyz: np.ndarray
    object_id: np.ndarray
    track_id: np.ndarray
    confidence: np.ndarray

    def to_cloud(self) -> PointCloud:
        """The ``/mosiv/surface_tracks`` cloud of this stamp."""
        return PointCloud(self.xyz, self.object_id, {"track_id": self.track_id.astype(np.uint32),
                                                     "confidence": self.confidence.astype(np.float32)},
                          stamp_ns=self.stamp_ns)

    @classmethod
    def empty(cls, stamp_ns: int) -> TrackPoints:
        """No track at ``stamp_ns`` (a frame without tracks)."""
        return cls(stamp_ns, np.zeros((0, 3)), np.zeros(0, np.uint16), np.zeros(0, np.uint32),
                   np.zeros(0, np.float32))

    @classmethod
    def from_cloud(cls, cloud: PointCloud) -> TrackPoints:
        """A ``/mosiv/surface_tracks`` cloud back; ValueError if it lacks a field."""
        missing = [name for name in TRACK_FIELDS if name not in cloud.fields]
        if missing:
            raise ValueError(f"surface track cloud of stamp {cloud.stamp_ns} ns lacks field(s) {missing}")
        return cls(cloud.stamp_ns, cloud.xyz.astype(np.float64), cloud.object_id,
                   np.asarray(cloud.fields["track_id"], np.uint32),
                   np.asarray(cloud.fields["confidence"], np.float32))


@dataclass
class SurfaceTracks:
    """Every track of a run of frames: ``positions`` (F, T, 3) m, NaN where track t is not alive.

    ``confidence`` (F, T), 0 where not alive; ``track_id`` and ``object_id`` (T,) per track,
    ``stamps_ns`` (F,) per frame. Tracks are in order of their id.
    """

    stamps_ns: np.ndarray
    track_id: np.ndarray
    object_id: np.ndarray
    positions: np.ndarray
    confidence: np.ndarray

    @classmethod
    def of(cls, frames: Sequence[TrackPoints]) -> SurfaceTracks:
        """The tracks of consecutive frames' points."""
        ids = np.unique(np.concatenate([f.track_id for f in frames] or [np.zeros(0, np.uint32)]))
        objects = np.zeros(len(ids), np.uint16)
        positions = np.full((len(frames), len(ids), 3), np.nan)
        confidence = np.zeros((len(frames), len(ids)))
        for k, points in enumerate(frames):
            column = np.searchsorted(ids, points.track_id)
            positions[k, column] = points.xyz
            confidence[k, column] = points.confidence
            objects[column] = points.object_id
        return cls(np.array([f.stamp_ns for f in frames], np.int64), ids.astype(np.uint32), objects,
                   positions, confidence)

    @property
    def alive(self) -> np.ndarray:
        """(F, T) bool: where each track has a point."""
        return np.isfinite(self.positions[..., 0])

    def from_frame(self, index: int) -> SurfaceTracks:
        """The tracks alive at frame ``index``, over the frames from it on (for attaching to particles)."""
        keep = self.alive[index]
        return SurfaceTracks(self.stamps_ns[index:], self.track_id[keep], self.object_id[keep],
                             self.positions[index:, keep], self.confidence[index:, keep])


@dataclass
class _Live:
    """One camera's live tracks: pixel positions (K, 2) (u, v), objects, ids, confidences."""

    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    object_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint16))
    track_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))
    confidence: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def select(self, keep: np.ndarray, uv: np.ndarray | None = None) -> _Live:
        return _Live((self.uv if uv is None else uv)[keep], self.object_id[keep], self.track_id[keep],
                     self.confidence[keep])

    @staticmethod
    def join(parts: Sequence[_Live]) -> _Live:
        return _Live(*(np.concatenate([getattr(p, name) for p in parts])
                       for name in ("uv", "object_id", "track_id", "confidence")))


class SurfaceTracker:
    """Surface tracks over a stream of frame sets, in stamp order (see the module docstring)."""

    def __init__(self, config: TrackConfig) -> None:
        if config.flow_tolerance <= 0 or config.spacing <= 0:
            raise ValueError(f"tracks.flow_tolerance and tracks.spacing must be positive, got "
                             f"{config.flow_tolerance}, {config.spacing}")
        self.tolerance = config.flow_tolerance
        self.spacing = config.spacing
        self.quality = config.quality
        self.flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        # Down to full resolution with small patches: an object may be only tens of pixels across
        # (the preset stops at half resolution, which doubled the tracks' drift on the sample bags).
        self.flow.setFinestScale(0)
        self.flow.setPatchSize(FLOW_PATCH)
        self.flow.setPatchStride(FLOW_PATCH // 3)
        self.previous: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # camera: (grey, labels)
        self.live: dict[str, _Live] = {}
        self.next_id = 0

    def update(self, stamp_ns: int, views: Sequence[View], objects: Mapping) -> TrackPoints:
        """Advance every camera's tracks to this frame set, seed new ones; the points alive now.

        ``objects``: the frame's ``ObjectGeometry`` by id (their voxels give the 3D points of a
        camera without depth). A camera absent from ``views`` loses its tracks.
        """
        now: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        points = []
        for view in views:
            grey = cv2.cvtColor(np.ascontiguousarray(view.rgb), cv2.COLOR_RGB2GRAY)
            now[view.camera] = (grey, view.labels)
            live = self.live.get(view.camera, _Live())
            if view.camera in self.previous and len(live.uv):
                live = self._advance(live, self.previous[view.camera], (grey, view.labels))
            else:
                live = _Live()
            live = _Live.join([live, self._seed(live, grey, view.labels, objects)])
            xyz = self._lift(view, live, objects)
            live = live.select(np.isfinite(xyz[:, 0]))
            points.append((xyz[np.isfinite(xyz[:, 0])], live))
            self.live[view.camera] = live
        self.previous = now
        self.live = {camera: self.live[camera] for camera in now}
        xyz = np.concatenate([p[0] for p in points] or [np.zeros((0, 3))])
        joined = _Live.join([p[1] for p in points]) if points else _Live()
        return TrackPoints(stamp_ns, xyz, joined.object_id, joined.track_id, joined.confidence)

    def _advance(self, live: _Live, before: tuple[np.ndarray, np.ndarray],
                 after: tuple[np.ndarray, np.ndarray]) -> _Live:
        """The tracks moved by the forward flow that pass the forward-backward check, per object."""
        kept = []
        for object_id in np.unique(live.object_id):
            mine = live.object_id == object_id
            first, second = (_isolate(grey, labels == object_id) for grey, labels in (before, after))
            if first is None or second is None:
                continue
            forward = self.flow.calc(first, second, None)
            backward = self.flow.calc(second, first, None)
            moved, error, ok = forward_backward(forward, backward, live.uv[mine], self.tolerance)
            ok &= _on_object(after[1] == object_id, moved)
            track = live.select(mine)
            track.confidence = track.confidence * (1.0 - (error / self.tolerance) ** 2)
            kept.append(track.select(ok, moved))
        return _Live.join(kept) if kept else _Live()

    def _seed(self, live: _Live, grey: np.ndarray, labels: np.ndarray, objects: Mapping) -> _Live:
        """New tracks at corners of each object farther than the spacing from its live tracks."""
        new = []
        for object_id in sorted(objects):
            inside = labels == object_id
            shrunk = cv2.erode(inside.astype(np.uint8), np.ones((3, 3), np.uint8))
            for uv in live.uv[live.object_id == object_id]:  # no seed near a live track
                cv2.circle(shrunk, (int(round(uv[0])), int(round(uv[1]))), int(np.ceil(self.spacing)), 0, -1)
            isolated = _isolate(grey, inside)
            if isolated is None or not shrunk.any():
                continue
            corners = cv2.goodFeaturesToTrack(isolated, maxCorners=0, qualityLevel=self.quality,
                                              minDistance=self.spacing, mask=shrunk)
            if corners is None:
                continue
            uv = corners.reshape(-1, 2).astype(np.float64)
            ids = np.arange(self.next_id, self.next_id + len(uv), dtype=np.uint32)
            self.next_id += len(uv)
            new.append(_Live(uv, np.full(len(uv), object_id, np.uint16), ids, np.ones(len(uv))))
        return _Live.join(new) if new else _Live()

    @staticmethod
    def _lift(view: View, live: _Live, objects: Mapping) -> np.ndarray:
        """World points (K, 3) of the tracks, NaN where there is none (see the module docstring)."""
        xyz = np.full((len(live.uv), 3), np.nan)
        if view.depth is not None:
            depth = _bilinear(view.depth, live.uv)
            ok = np.isfinite(depth)
            xyz[ok] = view.world_points(live.uv[ok, 0], live.uv[ok, 1], depth[ok])
            return xyz
        for object_id in np.unique(live.object_id):
            geometry = objects.get(int(object_id))
            mine = np.flatnonzero(live.object_id == object_id)
            if geometry is not None:
                xyz[mine] = view.first_hits(live.uv[mine, 0], live.uv[mine, 1], geometry.occupancy,
                                            geometry.voxel_size)
        return xyz


def forward_backward(forward: np.ndarray, backward: np.ndarray, uv: np.ndarray,
                     tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (K, 2) moved by a forward flow (H, W, 2), and the forward-backward check.

    (moved positions, error px, passed): the error is how far the backward flow at the moved
    position misses the start; a point passes when it is at most ``tolerance`` (NaN: outside
    the image, fails).
    """
    moved = uv + _bilinear(forward, uv)
    error = np.linalg.norm(moved + _bilinear(backward, moved) - uv, axis=1)
    with np.errstate(invalid="ignore"):
        return moved, error, error <= tolerance


def _isolate(grey: np.ndarray, inside: np.ndarray) -> np.ndarray | None:
    """The grey image with every pixel outside ``inside`` set to the mean inside (None if empty)."""
    if not inside.any():
        return None
    out = np.full_like(grey, int(round(float(grey[inside].mean()))))
    out[inside] = grey[inside]
    return out


def _corners(uv: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Top-left pixel (row, col) of the 2 x 2 pixels around each (u, v), the weights, and inside."""
    col0, row0 = np.floor(uv[:, 0]), np.floor(uv[:, 1])
    inside = (col0 >= 0) & (row0 >= 0) & (col0 < shape[1] - 1) & (row0 < shape[0] - 1)
    col0 = np.where(inside, col0, 0).astype(np.intp)
    row0 = np.where(inside, row0, 0).astype(np.intp)
    return row0, col0, np.stack([uv[:, 0] - col0, uv[:, 1] - row0], axis=1), inside


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear values of an (H, W) or (H, W, C) image at positions (K, 2).

    NaN outside the image, and wherever one of the four pixels is NaN.
    """
    row, col, weight, inside = _corners(uv, image.shape[:2])
    extra = (slice(None),) + (None,) * (image.ndim - 2)
    a, b = weight[extra + (0,)], weight[extra + (1,)]
    value = ((1 - a) * (1 - b) * image[row, col] + a * (1 - b) * image[row, col + 1]
             + (1 - a) * b * image[row + 1, col] + a * b * image[row + 1, col + 1])
    return np.where(inside[extra], value, np.nan)


def _on_object(inside: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(K,) bool: all four pixels around each position are the object's."""
    row, col, _, ok = _corners(np.nan_to_num(uv, nan=-1.0), inside.shape)
    return ok & inside[row, col] & inside[row, col + 1] & inside[row + 1, col] & inside[row + 1, col + 1]
