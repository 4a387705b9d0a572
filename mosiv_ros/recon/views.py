"""One camera's view of one frame, prepared for carving: projection, filtered labels, distances.

What it is for: turning a calibrated ``Camera`` and its ``Frame`` into what the carving rules of
``carving`` ask of a view: where a world point lands in the image and at what depth, the instance
label and depth there, and how many pixels of a given object, or of any object, a rectangle of
pixels holds (summed-area tables, O(1) per rectangle). Back the other way, for surface points,
their colours and surface tracks: the world point of a pixel at a depth, and where a pixel's ray
first enters an object's occupied voxels. Also the majority filter that cleans noisy instance masks and the
automatic reconstruction box.
What it is not for: deciding occupancy (``carving``) or assembling frames from topics
(``mosiv_ros.io.streams``).

Pixel centres are at integer coordinates (ROS/OpenCV), so a projection (u, v) falls in pixel
(round(v), round(u)).
"""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np

from mosiv_ros.io.recording import Camera, Frame


def majority_filter(labels: np.ndarray, size: int) -> np.ndarray:
    """Each pixel takes the most frequent label of its ``size`` x ``size`` window.

    Removes isolated wrong pixels (salt-and-pepper mask noise) and one-pixel jags on silhouette
    boundaries. Ties keep the pixel's own label. ``size`` <= 1 returns the labels unchanged.
    """
    if size <= 1:
        return labels
    if size % 2 == 0:
        raise ValueError(f"mask_filter must be odd, got {size}")
    ids = np.unique(labels)
    if len(ids) == 1:
        return labels
    best = np.full(labels.shape, -1.0, dtype=np.float32)
    out = labels.copy()
    for label in ids:
        own = (labels == label).astype(np.float32)
        # Window count of this label, plus half a vote for the pixel's own label (tie-break).
        votes = cv2.boxFilter(own, -1, (size, size), normalize=False,
                              borderType=cv2.BORDER_REPLICATE) + 0.5 * own
        better = votes > best
        out[better] = label
        best[better] = votes[better]
    return out


def _summed_area(pixels: np.ndarray) -> np.ndarray:
    """(H + 1, W + 1) table whose [r, c] counts the True pixels above-left of (r, c)."""
    table = np.zeros((pixels.shape[0] + 1, pixels.shape[1] + 1), dtype=np.int64)
    table[1:, 1:] = pixels.cumsum(axis=0, dtype=np.int64).cumsum(axis=1)
    return table


OCCLUDED = -1
"""Label of a pixel that a known occluder the masks leave out covers (``View.silhouette_labels``):
neither background nor an object's, so unknown for every object."""


class View:
    """One calibrated camera's labels (and depth) at one stamp, queried at world points."""

    def __init__(self, camera: Camera, frame: Frame, *, mask_filter: int, use_depth: bool) -> None:
        self.camera = camera.name
        self.intrinsics = camera.intrinsics
        self.T_optical_world = np.linalg.inv(camera.T_world_optical)
        self.labels = majority_filter(frame.mask, mask_filter)
        self.mask = frame.mask
        """The mask as recorded: a pixel's colour is an object's only where both labels agree."""
        self.rgb = frame.rgb
        self.depth = frame.depth if use_depth else None
        self.height, self.width = self.labels.shape
        self.focal = float(max(self.intrinsics.K[0, 0], self.intrinsics.K[1, 1]))
        self.distorted = bool(np.any(self.intrinsics.D))
        self.ids = frozenset(int(i) for i in np.unique(self.labels) if i != 0)
        self._any = _summed_area(self.labels != 0)
        self._object: dict[int, np.ndarray] = {}
        self.occluder: np.ndarray | None = None
        """(H, W) depth of a known unlabelled occluder in front of each pixel (``hide_behind``)."""
        self._occluder_minima: np.ndarray | None = None

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, v, z) of world points (N, 3), each (N,).

        u, v: pixel coordinates, NaN behind the camera; z: depth along the optical axis.
        """
        R, t = self.T_optical_world[:3, :3], self.T_optical_world[:3, 3]
        X, Y, Z = points[:, 0], points[:, 1], points[:, 2]
        # Column by column: much faster than an (N, 3) @ (3, 3) product in numpy.
        x = R[0, 0] * X + R[0, 1] * Y + R[0, 2] * Z + t[0]
        y = R[1, 0] * X + R[1, 1] * Y + R[1, 2] * Z + t[1]
        z = R[2, 0] * X + R[2, 1] * Y + R[2, 2] * Z + t[2]
        if self.distorted:
            uv = self.intrinsics.project(np.stack([x, y, z], axis=1))
            return uv[:, 0], uv[:, 1], z
        K = self.intrinsics.K
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse_z = np.where(z > 0, 1.0 / z, np.nan)
        return (K[0, 0] * x + K[0, 1] * y) * inverse_z + K[0, 2], K[1, 1] * y * inverse_z + K[1, 2], z

    def pixels(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, inside): the pixel each projection falls in, and whether it is in the image.

        row and col are 0 where the projection is outside the image.
        """
        with np.errstate(invalid="ignore"):
            col = np.floor(u + 0.5)
            row = np.floor(v + 0.5)
            inside = (col >= 0) & (col < self.width) & (row >= 0) & (row < self.height)
        return np.where(inside, row, 0).astype(np.intp), np.where(inside, col, 0).astype(np.intp), inside

    def count_any(self, r0: np.ndarray, r1: np.ndarray, c0: np.ndarray, c1: np.ndarray) -> np.ndarray:
        """Pixels of any object in the rectangles rows r0..r1, columns c0..c1 (inclusive, inside)."""
        return _rectangles(self._any, r0, r1, c0, c1)

    def count_object(self, object_id: int, r0: np.ndarray, r1: np.ndarray, c0: np.ndarray,
                     c1: np.ndarray) -> np.ndarray:
        """Pixels of ``object_id`` in the rectangles (as ``count_any``)."""
        if object_id not in self._object:
            self._object[object_id] = _summed_area(self.labels == object_id)
        return _rectangles(self._object[object_id], r0, r1, c0, c1)

    def hide_behind(self, depth: np.ndarray) -> None:
        """Mark where a known occluder that the masks leave out (the declared gripper) lies.

        ``depth`` (H, W) is its depth at each pixel, inf where it is not: a background pixel
        hides what lies behind it there instead of carving it (``carving``).
        """
        self.occluder = np.asarray(depth, dtype=np.float32)
        self._occluder_minima = None

    def silhouette_labels(self) -> np.ndarray:
        """The labels as the 2D loss reads them: ``OCCLUDED`` where a known occluder covers background.

        There the occluder may hide any object, as another object's pixel may (``hide_behind``).
        """
        if self.occluder is None:
            return self.labels
        return np.where((self.labels == 0) & np.isfinite(self.occluder), OCCLUDED,
                        self.labels.astype(np.int32))

    def nearest_occluder(self, r0: np.ndarray, r1: np.ndarray, c0: np.ndarray,
                         c1: np.ndarray) -> np.ndarray:
        """The least ``occluder`` depth in the rectangles (as ``count_any``; inf without one).

        Exact minima from a sparse table: the least of four blocks of power-of-two sides that
        cover the rectangle.
        """
        if self.occluder is None:
            return np.full(np.shape(r0), np.inf)
        if self._occluder_minima is None:
            self._occluder_minima = _sparse_minima(self.occluder)
        table = self._occluder_minima
        a = np.log2(r1 - r0 + 1).astype(np.intp)
        b = np.log2(c1 - c0 + 1).astype(np.intp)
        r_end, c_end = r1 - (1 << a) + 1, c1 - (1 << b) + 1
        return np.minimum(np.minimum(table[a, b, r0, c0], table[a, b, r_end, c0]),
                          np.minimum(table[a, b, r0, c_end], table[a, b, r_end, c_end]))

    def touches_border(self, object_id: int) -> bool:
        """Whether the object's silhouette reaches the image border (it may extend beyond it)."""
        edges = (self.labels[0], self.labels[-1], self.labels[:, 0], self.labels[:, -1])
        return any(bool(np.any(edge == object_id)) for edge in edges)

    def surface_points(self, object_id: int) -> tuple[np.ndarray, np.ndarray]:
        """World points (M, 3) of the object's pixels with a finite depth, and their colours (M, 3).

        Both empty without depth.
        """
        if self.depth is None:
            return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        row, col = np.nonzero((self.labels == object_id) & np.isfinite(self.depth))
        return self.world_points(col, row, self.depth[row, col]), self.rgb[row, col]

    @property
    def centre(self) -> np.ndarray:
        """The camera's optical centre in world (3,)."""
        return np.linalg.inv(self.T_optical_world)[:3, 3]

    def rays(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """World directions (M, 3) of the rays through pixel coordinates (u, v), optical z = 1."""
        u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
        if self.distorted:
            rays = _undistort(self.intrinsics, u, v)
        else:
            rays = np.stack([u, v, np.ones_like(u)], axis=1) @ np.linalg.inv(self.intrinsics.K).T
        return rays @ self.T_optical_world[:3, :3]

    def world_points(self, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
        """World points (M, 3) at depth ``z`` (along the optical axis) behind pixel coordinates (u, v)."""
        return self.centre + self.rays(u, v) * np.asarray(z, dtype=np.float64)[:, None]

    def first_hits(self, u: np.ndarray, v: np.ndarray, voxel_centres: np.ndarray,
                   voxel_size: float) -> np.ndarray:
        """Where the rays through (u, v) first enter the voxels (M, 3); NaN where they miss.

        Marched in steps of a quarter voxel, so a hit lies at most that far inside the surface of
        the voxels (the visual hull, for carved voxels).
        """
        hits = np.full((len(np.atleast_1d(u)), 3), np.nan)
        if len(voxel_centres) == 0 or len(hits) == 0:
            return hits
        lo = voxel_centres.min(axis=0) - voxel_size / 2
        index = np.round((voxel_centres - lo) / voxel_size - 0.5).astype(np.int64)
        grid = np.zeros(index.max(axis=0) + 1, dtype=bool)
        grid[tuple(index.T)] = True
        hi = lo + np.asarray(grid.shape) * voxel_size
        origin, direction = self.centre, self.rays(u, v)
        with np.errstate(divide="ignore", invalid="ignore"):  # slab test against the voxels' box
            t0, t1 = (lo - origin) / direction, (hi - origin) / direction
        enter = np.nanmax(np.minimum(t0, t1), axis=1).clip(0.0)
        leave = np.nanmin(np.maximum(t0, t1), axis=1)
        step = voxel_size / 4 / np.linalg.norm(direction, axis=1)
        todo = np.flatnonzero(enter < leave)
        t = enter[todo] + step[todo] / 2
        while len(todo):
            point = origin + direction[todo] * t[:, None]
            cell = np.floor((point - lo) / voxel_size).astype(np.int64)
            inside = np.all((cell >= 0) & (cell < grid.shape), axis=1)
            hit = inside.copy()
            hit[inside] = grid[tuple(cell[inside].T)]
            hits[todo[hit]] = point[hit]
            t = t + step[todo]
            going = ~hit & (t < leave[todo])
            todo, t = todo[going], t[going]
        return hits


def _sparse_minima(image: np.ndarray) -> np.ndarray:
    """Range minima of ``image``: (A, B, H, W), [a, b, r, c] the least over a block.

    The block is rows r..r + 2^a - 1 and columns c..c + 2^b - 1, clipped at the image's edges.
    """
    height, width = image.shape
    rows = [image]
    for a in range(1, int(np.log2(height)) + 1):
        below = np.full_like(image, np.inf)
        below[:height - (1 << (a - 1))] = rows[-1][1 << (a - 1):]
        rows.append(np.minimum(rows[-1], below))
    table = np.empty((len(rows), int(np.log2(width)) + 1, height, width), dtype=image.dtype)
    for a, row in enumerate(rows):
        table[a, 0] = row
        for b in range(1, table.shape[1]):
            right = np.full_like(image, np.inf)
            right[:, :width - (1 << (b - 1))] = table[a, b - 1][:, 1 << (b - 1):]
            table[a, b] = np.minimum(table[a, b - 1], right)
    return table


def _rectangles(table: np.ndarray, r0: np.ndarray, r1: np.ndarray, c0: np.ndarray,
                c1: np.ndarray) -> np.ndarray:
    return table[r1 + 1, c1 + 1] - table[r0, c1 + 1] - table[r1 + 1, c0] + table[r0, c0]


def _undistort(intrinsics, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Normalised rays (x, y, 1) of distorted pixels (plumb_bob), by OpenCV's iterative inverse."""
    pixels = np.stack([u, v], axis=1).astype(np.float64).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(pixels, intrinsics.K, intrinsics.D).reshape(-1, 2)
    return np.concatenate([xy, np.ones((len(xy), 1))], axis=1)


def look_at_box(cameras: Iterable[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the automatic reconstruction box of an inward-looking rig.

    A cube around the point nearest to every optical axis, reaching the farthest camera. With a
    single camera, or axes too close to parallel to meet, the cube is centred 1 m in front of the
    cameras' mean position instead.
    """
    centres, axes = [], []
    for camera in cameras:
        centres.append(camera.T_world_optical[:3, 3])
        axes.append(camera.T_world_optical[:3, 2])
    if not centres:
        raise ValueError("no cameras to place the reconstruction box around")
    centres, axes = np.array(centres), np.array(axes)
    # Least-squares point nearest to the lines c_i + s d_i: sum (I - d d^T)(p - c_i) = 0.
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centres, axes, strict=True):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    if len(centres) > 1 and np.linalg.cond(A) < 1e6:
        point = np.linalg.solve(A, b)
    else:
        point = centres.mean(axis=0) + axes.mean(axis=0)
    half = max(float(np.max(np.linalg.norm(centres - point, axis=1))), 0.5)
    return point - half, point + half
