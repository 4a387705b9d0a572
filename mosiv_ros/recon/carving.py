"""Per-object space carving on a voxel lattice, coarse to fine, with occlusion-aware rules.

What it is for: the occupied voxels of one object at one stamp, from several ``View``s. A voxel
is kept when (1) no view says it is empty, (2) it projects into at least ``min_views`` images and
(3) at least one view shows the object there, or a known occluder hides it and the object
continues there (below). A view says "empty" when the voxel projects onto a
background pixel, or, with depth, lies in front of the measured surface by more than the depth
tolerance (free space, whatever the label). A pixel of *another* object is unknown, not empty: it
may hide this one. Pixels outside an image are unknown too. Below a known ground plane nothing is
kept (no camera can see there, so carving alone would keep the object's shadow in the ground).
A known occluder the masks leave out (the declared gripper, ``recon.gripper``; ``View.occluder``)
makes the background pixels where it lies in front of a voxel unknown too, and the space it
fills (``inside``) empty. What it hides from every camera may be the object's: a cube's top
under a pressing plate is, and without (3)'s second clause it was lost. But so is the space
under the plate's overhang beside the cube, which no view can tell from the cube's top. A
hidden voxel is kept where the object continues it away from the occluder: marching from it
along ``away`` (the direction from the occluder's nearest point, the way it presses) through
hidden voxels reaches a voxel a view shows as the object before an empty one. So the cube's top
is kept above what the cameras show of its sides, the overhang's space (empty below it) is not,
and neither is the space under a gripper that holds nothing.
What it is not for: separating objects from each other or extracting surfaces (``reconstruct``).

Coarse to fine: cells of 2^l voxels are tested conservatively, survivors split into 8, down to
single voxels tested at their centres. A cell's footprint in a view is the rectangle of pixels
its voxel centres can fall in (from its projected corners); the cell is dropped only if, in some
view, that rectangle lies in the image and holds no object pixel, or if no view's rectangle holds
a pixel of the object. Depth is used at the voxel level only.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from mosiv_ros.recon.views import View

_LOG = logging.getLogger(__name__)

COARSEST_CELLS = 16
"""Cells per axis, at most, of the coarsest carving level."""
DISTORTION_MARGIN_PX = 1.0
"""Extra pixels around a footprint under lens distortion (which bends a cell's projected edges)."""
_CHILDREN = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int64)
_CORNERS = 2.0 * _CHILDREN - 1.0


@dataclass(frozen=True)
class Lattice:
    """A regular voxel grid: voxel (i, j, k) spans origin + [i, i+1) * voxel_size, etc."""

    origin: np.ndarray
    voxel_size: float
    shape: tuple[int, int, int]

    @classmethod
    def covering(cls, lo: Sequence[float], hi: Sequence[float], voxel_size: float) -> Lattice:
        """The lattice of ``voxel_size`` with origin a multiple of it, covering lo..hi."""
        if voxel_size <= 0:
            raise ValueError(f"voxel_size must be positive, got {voxel_size}")
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        if lo.shape != (3,) or hi.shape != (3,) or np.any(hi <= lo):
            raise ValueError(f"workspace must be lo < hi in x, y, z; got {lo.tolist()}, {hi.tolist()}")
        origin = np.floor(lo / voxel_size) * voxel_size
        shape = np.ceil((hi - origin) / voxel_size - 1e-9).astype(int)
        return cls(origin, float(voxel_size), (int(shape[0]), int(shape[1]), int(shape[2])))

    def centres(self, index: np.ndarray, level: int = 0) -> np.ndarray:
        """World centres (N, 3) of cells (N, 3) of 2^level voxels."""
        size = self.voxel_size * (1 << level)
        return self.origin + (index + 0.5) * size

    def linear(self, index: np.ndarray) -> np.ndarray:
        """Flat int64 index of voxels (N, 3)."""
        return np.ravel_multi_index(index.T, self.shape).astype(np.int64)


def carve_object(
    views: Sequence[View],
    object_id: int,
    lattice: Lattice,
    *,
    min_views: int,
    depth_tolerance: float,
    ground: tuple[np.ndarray, float] | None = None,
    inside: Callable[[np.ndarray], np.ndarray] | None = None,
    away: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """Voxel indices (N, 3) int64 occupied by ``object_id`` (see the module docstring's rules).

    ``ground`` (unit normal n, height h): only voxels with n . centre >= h are kept. ``inside``:
    which world points an occluder fills (none of its voxels is kept).
    """
    shape = np.array(lattice.shape)
    level = max(0, math.ceil(math.log2(max(shape.max() / COARSEST_CELLS, 1.0))))
    top = -(-shape // (1 << level))
    cells = np.stack(np.meshgrid(*[np.arange(n) for n in top], indexing="ij"), -1).reshape(-1, 3)
    while level > 0:
        keep = _keep_cells(views, object_id, lattice, cells, level, min_views, depth_tolerance)
        if ground is not None:
            radius = lattice.voxel_size * (1 << level) * math.sqrt(3.0) / 2.0
            keep &= lattice.centres(cells, level) @ ground[0] + radius >= ground[1]
        cells = cells[keep]
        level -= 1
        cells = (2 * cells[:, None, :] + _CHILDREN[None]).reshape(-1, 3)
        cells = cells[np.all(cells < -(-shape // (1 << level)), axis=1)]
    cells = cells[np.all(cells < shape, axis=1)]
    if ground is not None:
        cells = cells[lattice.centres(cells) @ ground[0] >= ground[1]]
    if inside is not None:
        cells = cells[~inside(lattice.centres(cells))]
    keep, shown = _keep_voxels(views, object_id, lattice, cells, min_views, depth_tolerance)
    cells, shown = cells[keep], shown[keep]
    if shown.all():
        return cells
    if away is None:
        return cells[shown]
    return cells[shown | _continued(cells, shown, away(lattice.centres(cells)))]


def _continued(cells: np.ndarray, shown: np.ndarray, away: np.ndarray) -> np.ndarray:
    """Which ``cells`` (N, 3) reach a ``shown`` cell through kept ones marching along ``away`` (N, 3).

    Half-voxel steps from each cell's centre; a march ends at a shown cell (continued), or at a
    cell not kept or past the cells' box (not).
    """
    lo = cells.min(axis=0)
    state = np.zeros(tuple(cells.max(axis=0) - lo + 1), dtype=np.int8)  # 0 empty, 1 hidden, 2 shown
    state[tuple((cells - lo).T)] = np.where(shown, 2, 1)
    todo = np.flatnonzero(~shown & np.any(away != 0, axis=1))
    found = shown.copy()
    position = (cells[todo] - lo + 0.5).astype(np.float64)
    while len(todo):  # every step moves half a voxel: the box's diagonal bounds the steps
        position += 0.5 * away[todo]
        index = np.floor(position).astype(np.int64)
        inside = np.all((index >= 0) & (index < state.shape), axis=1)
        at = np.zeros(len(todo), dtype=np.int8)
        at[inside] = state[tuple(index[inside].T)]
        found[todo[at == 2]] = True
        going = at == 1
        todo, position = todo[going], position[going]
    return found


def _keep_cells(views: Sequence[View], object_id: int, lattice: Lattice, cells: np.ndarray,
                level: int, min_views: int, depth_tolerance: float) -> np.ndarray:
    """Conservative test of cells of 2^level voxels: False only where the voxels surely fail."""
    half = lattice.voxel_size * (1 << level) / 2.0
    corners = (lattice.centres(cells, level)[:, None, :] + half * _CORNERS[None]).reshape(-1, 3)
    carved = np.zeros(len(cells), dtype=bool)
    seen = np.zeros(len(cells), dtype=np.int32)
    evidence = np.zeros(len(cells), dtype=bool)
    for view in views:
        u, v, z = view.project(corners)
        u, v = u.reshape(-1, 8), v.reshape(-1, 8)
        # A cell reaching the camera plane has no bounded footprint: it decides nothing.
        straddles = np.any(z.reshape(-1, 8) <= 0, axis=1)
        u, v = np.where(straddles[:, None], 0.0, u), np.where(straddles[:, None], 0.0, v)
        pad = DISTORTION_MARGIN_PX if view.distorted else 0.0
        c0, r0 = (np.floor(a.min(axis=1) - pad + 0.5).astype(np.int64) for a in (u, v))
        c1, r1 = (np.floor(a.max(axis=1) + pad + 0.5).astype(np.int64) for a in (u, v))
        within = ~straddles & (c0 >= 0) & (r0 >= 0) & (c1 < view.width) & (r1 < view.height)
        touches = straddles | ((c1 >= 0) & (r1 >= 0) & (c0 < view.width) & (r0 < view.height))
        box = (np.clip(r0, 0, view.height - 1), np.clip(r1, 0, view.height - 1),
               np.clip(c0, 0, view.width - 1), np.clip(c1, 0, view.width - 1))
        empty = within & (view.count_any(*box) == 0)
        # The object may be there: its pixels are in the footprint, or part of the footprint
        # lies outside the image, or the cell reaches the camera plane.
        evidence |= (touches & ~within) | (within & (view.count_object(object_id, *box) > 0))
        if view.occluder is not None:
            nearest, farthest = view.nearest_occluder(*box), z.reshape(-1, 8).max(axis=1)
            empty &= nearest >= farthest - depth_tolerance  # no known occluder in front of the cell
            evidence |= within & (nearest < farthest)  # which may hide some of its voxels
        carved |= empty
        seen += touches
    return ~carved & (seen >= min_views) & evidence


def _keep_voxels(views: Sequence[View], object_id: int, lattice: Lattice, voxels: np.ndarray,
                 min_views: int, depth_tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact test of single voxels at their centres: which are kept, which a view shows."""
    centres = lattice.centres(voxels)
    empty = np.zeros(len(voxels), dtype=bool)
    seen = np.zeros(len(voxels), dtype=np.int32)
    evidence = np.zeros(len(voxels), dtype=bool)
    hidden = np.zeros(len(voxels), dtype=bool)
    for view in views:
        u, v, z = view.project(centres)
        row, col, inside = view.pixels(u, v)
        label = view.labels[row, col]
        background = inside & (label == 0)
        if view.occluder is not None:  # a known occluder in front hides the voxel
            behind = inside & (view.occluder[row, col] < z - depth_tolerance)
            background &= ~behind
            hidden |= behind
        empty |= background
        if view.depth is not None:
            depth = view.depth[row, col]
            with np.errstate(invalid="ignore"):
                empty |= inside & (z < depth - depth_tolerance)
        seen += inside
        evidence |= inside & (label == object_id)
    return ~empty & (seen >= min_views) & (evidence | hidden), evidence
