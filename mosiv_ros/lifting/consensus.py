"""Temporal consensus of each object's occupancy over the first observed frames, before lifting.

What it is for: a visual hull only bounds an object from outside, and where another object hides
it from a view, that view cannot carve (occlusion-aware carving calls such pixels unknown). So in
the frame that is lifted, an object partly hidden behind another can carry a phantom: hull that
the next frames, seen from other angles as the objects move apart, do not have. The lifted
particles would keep it for the whole fit. ``consensus`` intersects each object's voxels in the
lifted frame with its voxels in a few later frames, each moved back by the whole-voxel
translation that best overlaps it with the lifted frame, and dilated by one voxel (the motion is
not a whole number of voxels). For a body that moves rigidly, every frame's hull contains it, so
the intersection does too and only loses what some frame shows empty.

A later frame whose aligned hull would remove more than ``max_removed`` of the object's voxels
is not used for that object (logged): the object deformed, turned or was cut from a view, and
the intersection would eat into it; phantoms are a few per cent of an object, a column of sand
starting to collapse loses 1 % in the first frame and 15 % by the second.

What it is not for: carving (``recon.carving``) or filling objects with particles (``lift``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from scipy import ndimage

from mosiv_ros.io.recording import PointCloud
from mosiv_ros.recon.reconstruct import VOXEL_FIELD

_LOG = logging.getLogger(__name__)

SEARCH_VOXELS = 2
"""Whole voxels searched around the centroid shift for the best-overlapping translation."""
_STEPS = range(-SEARCH_VOXELS, SEARCH_VOXELS + 1)
_SHIFTS = np.array(sorted(([i, j, k] for i in _STEPS for j in _STEPS for k in _STEPS),
                          key=lambda s: (s[0] ** 2 + s[1] ** 2 + s[2] ** 2, s)), dtype=np.int64)


def consensus(cloud: PointCloud, later: Sequence[PointCloud], max_removed: float) -> PointCloud:
    """``cloud`` with each object's voxels cut to those every usable later frame agrees with.

    Surface points are left as they are.
    """
    sizes = np.asarray(cloud.fields[VOXEL_FIELD], dtype=np.float64)
    voxel = sizes > 0
    keep = np.ones(len(cloud.xyz), dtype=bool)
    for object_id in sorted(int(i) for i in np.unique(cloud.object_id[voxel])):
        mine = np.flatnonzero(voxel & (cloud.object_id == object_id))
        size = float(sizes[mine].max())
        cells = _cells(cloud.xyz[mine], size)
        kept = np.ones(len(mine), dtype=bool)
        for other in later:
            theirs = (other.object_id == object_id) & np.isclose(other.fields[VOXEL_FIELD], size)
            if not theirs.any():
                continue
            agree = _agreeing(cells[kept], _cells(other.xyz[theirs], size))
            removed = 1.0 - agree.mean()
            if removed > max_removed:
                _LOG.info("object %d: its hull at stamp %d ns, moved onto the lifted one, would "
                          "remove %.0f%% of it (> %.0f%%: it deformed, turned or left a view); that "
                          "frame is not used to trim it", object_id, other.stamp_ns, 100 * removed,
                          100 * max_removed)
                continue
            kept[np.flatnonzero(kept)[~agree]] = False
        if not kept.all():
            _LOG.info("object %d: %d of %d voxels of stamp %d ns are hull no later frame shows; "
                      "trimmed before lifting", object_id, int((~kept).sum()), len(kept), cloud.stamp_ns)
        keep[mine[~kept]] = False
    fields = {name: np.asarray(values)[keep] for name, values in cloud.fields.items()}
    return PointCloud(cloud.xyz[keep], cloud.object_id[keep], fields, cloud.stamp_ns, cloud.frame_id)


def _cells(centres: np.ndarray, size: float) -> np.ndarray:
    """Integer lattice index (N, 3) of voxel centres (the lattice's origin is a multiple of size)."""
    return np.round(np.asarray(centres, dtype=np.float64) / size - 0.5).astype(np.int64)


def _agreeing(cells: np.ndarray, other: np.ndarray) -> np.ndarray:
    """Which of ``cells`` lie within one voxel of ``other`` translated onto them (best overlap)."""
    guess = np.round(other.mean(axis=0) - cells.mean(axis=0)).astype(np.int64)
    pad = SEARCH_VOXELS + 1
    lo = cells.min(axis=0) - pad
    grid = np.zeros(cells.max(axis=0) - lo + pad + 1, dtype=bool)
    grid[tuple((cells - lo).T)] = True
    best, best_count = guess, -1
    for shift in _SHIFTS + guess:  # nearest the guess first: ties go to it
        count = int(_occupied(grid, other - shift - lo).sum())
        if count > best_count:
            best, best_count = shift, count
    moved = other - best - lo
    inside = np.all((moved >= 0) & (moved < grid.shape), axis=1)
    support = np.zeros_like(grid)
    support[tuple(moved[inside].T)] = True
    support = ndimage.binary_dilation(support, structure=np.ones((3, 3, 3), dtype=bool))
    return support[tuple((cells - lo).T)]


def _occupied(grid: np.ndarray, index: np.ndarray) -> np.ndarray:
    """grid[index] for indices (N, 3), False outside the grid."""
    inside = np.all((index >= 0) & (index < grid.shape), axis=1)
    out = np.zeros(len(index), dtype=bool)
    out[inside] = grid[tuple(index[inside].T)]
    return out
