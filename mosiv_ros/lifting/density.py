"""Density fields and signed distances of one object on a box of the particle lattice.

What it is for: the grid-level steps of lifting (MOSIV stage 2): resample an object's observed
occupancy (voxel centres of any voxel size) onto the particle lattice, smooth it into a density
field and refine it so that thin parts are not eroded, and compute signed distances to the
resulting surface. What it is not for: choosing particles or resolving overlaps between objects
(``lift``).

The particle lattice has spacing h and cell centres at (n + 1/2) h for integer n (world-aligned,
so every object and every run shares it). A ``Box`` is an axis-aligned block of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class Box:
    """Cells lo .. lo + shape - 1 (integer lattice indices) of the lattice of spacing h."""

    lo: np.ndarray
    shape: tuple[int, int, int]
    h: float

    @classmethod
    def around(cls, points: np.ndarray, half_extent: float, margin: float, h: float) -> Box:
        """The cells covering the bounding box of ``points`` grown by half_extent + margin."""
        lo = np.floor((points.min(axis=0) - half_extent - margin) / h).astype(np.int64)
        hi = np.ceil((points.max(axis=0) + half_extent + margin) / h).astype(np.int64)
        shape = hi - lo
        return cls(lo, (int(shape[0]), int(shape[1]), int(shape[2])), h)

    @classmethod
    def of_cells(cls, cells: np.ndarray, margin: float, h: float) -> Box:
        """The cells covering lattice cells (N, 3) grown by ``margin`` metres."""
        pad = int(np.ceil(margin / h))
        lo = cells.min(axis=0) - pad
        shape = cells.max(axis=0) + pad + 1 - lo
        return cls(lo, (int(shape[0]), int(shape[1]), int(shape[2])), h)

    def centres(self, cells: np.ndarray) -> np.ndarray:
        """World centres (N, 3) of local cell indices (N, 3)."""
        return (self.lo + cells + 0.5) * self.h


def occupancy_on_lattice(voxel_centres: np.ndarray, voxel_size: float, box: Box) -> np.ndarray:
    """Bool grid of ``box``: the cells of the occupied voxels, by centre or by half coverage.

    A cell no larger than the voxels is inside when its centre lies in an occupied voxel; a
    larger cell when the voxels cover at least half of it. (Counting every cell that holds any
    voxel centre would grow each object by up to a cell: +33 % on a 4 cm ball at 1 cm spacing.
    Testing larger cells by their centre would decide ties by rounding where cell centres lie on
    voxel faces, as they all do at h = 2 voxels: each object grew a layer on its low sides
    only.) A less covered cell is inside only where none of its neighbours is: thin parts stay
    one cell thick instead of vanishing. The voxels may be of any size (the reconstruction's);
    their lattice is recovered from the centres themselves: voxel i spans centre_i +-
    voxel_size / 2.
    """
    if box.h <= voxel_size:
        ref = voxel_centres.min(axis=0)
        index = np.round((voxel_centres - ref) / voxel_size).astype(np.int64)
        occupied = np.zeros(index.max(axis=0) + 1, dtype=bool)
        occupied[tuple(index.T)] = True
        axes = [(box.lo[a] + np.arange(box.shape[a]) + 0.5) * box.h for a in range(3)]
        # Per axis, which voxel slab each cell centre falls in (-1 outside the occupied block).
        slabs = []
        for a in range(3):
            q = np.round((axes[a] - ref[a]) / voxel_size).astype(np.int64)
            slabs.append(np.where((q >= 0) & (q < occupied.shape[a]), q, -1))
        grid = occupied[np.ix_(*(np.maximum(s, 0) for s in slabs))]
        grid &= (slabs[0] >= 0)[:, None, None] & (slabs[1] >= 0)[None, :, None] & (slabs[2] >= 0)[None, None, :]
    else:
        holding = np.floor(voxel_centres / box.h).astype(np.int64) - box.lo
        inside = np.all((holding >= 0) & (holding < np.asarray(box.shape)), axis=1)
        coverage = np.zeros(box.shape, dtype=np.float64)
        np.add.at(coverage, tuple(holding[inside].T), (voxel_size / box.h) ** 3)
        grid = coverage >= 0.5 - 1e-6  # a tie (half covered) is covered; voxel sizes come as float32
        # a part thinner than half a cell (a plate, a rod) has no such cell: keep the cells it
        # touches where no neighbour is inside, so it is not eroded away
        # (no neighbour in any of the 26 directions: a rim cell touching the inside only
        # diagonally would otherwise start an extra layer that the refinement completes)
        grid |= (coverage > 0) & ~ndimage.binary_dilation(grid, structure=np.ones((3, 3, 3), bool))
    return grid


def refine_density(occupied: np.ndarray, iterations: int, threshold: float) -> np.ndarray:
    """Inside cells of the refined density field (MOSIV stage 2).

    Rounds of 3x3x3 mean filtering, each followed by resetting the occupied cells to density 1,
    then thresholding. The reset keeps every occupied cell inside (thin parts are never eroded); the filtering adds
    cells mostly surrounded by occupied ones (cracks, pits and pinholes fill, the boundary smooths).
    """
    density = occupied.astype(np.float32)
    for _ in range(iterations):
        density = ndimage.uniform_filter(density, size=3, mode="constant")
        density[occupied] = 1.0
    return density >= threshold


def signed_distance(inside: np.ndarray, h: float) -> np.ndarray:
    """Signed distance (m) of every cell centre to the surface of the ``inside`` cells.

    Negative inside; the surface lies halfway between inside and outside cells (+-h/2 next to it).
    """
    if not inside.any():
        return np.full(inside.shape, np.inf)
    outside_distance = ndimage.distance_transform_edt(~inside, sampling=h)
    inside_distance = ndimage.distance_transform_edt(inside, sampling=h)
    return np.where(inside, h / 2 - inside_distance, outside_distance - h / 2)


def voxel_surface_distance(voxel_centres: np.ndarray, voxel_size: float, box: Box,
                           iterations: int, threshold: float) -> np.ndarray:
    """Signed distance (m) of every cell centre of ``box`` to the surface of the voxels themselves.

    For a lattice coarser than the voxels: ``signed_distance`` of the lattice's inside cells places
    the surface only to within a cell (every outermost inside cell is at -h/2), this one to within
    a voxel. The voxels are refined as the lattice is (``refine_density``, so a filled pinhole is
    no surface), their signed distances taken at their centres and interpolated trilinearly to
    the cell centres. The voxels lie on the lattice of ``voxel_size`` through the origin (voxel i
    spans [i, i + 1) * voxel_size, as the reconstruction's does), the same alignment by which
    ``occupancy_on_lattice`` counts a coarser cell's coverage.
    """
    index = np.round(voxel_centres / voxel_size - 0.5).astype(np.int64)
    ratio = box.h / voxel_size
    lo = np.minimum(index.min(axis=0), np.floor(box.lo * ratio).astype(np.int64)) - 1
    hi = np.maximum(index.max(axis=0), np.ceil((box.lo + np.asarray(box.shape)) * ratio).astype(np.int64)) + 1
    occupied = np.zeros(hi - lo + 1, dtype=bool)
    occupied[tuple((index - lo).T)] = True
    sdf = signed_distance(refine_density(occupied, iterations, threshold), voxel_size)
    axes = [(box.lo[a] + np.arange(box.shape[a]) + 0.5) * ratio - 0.5 - lo[a] for a in range(3)]
    coords = np.stack(np.meshgrid(*axes, indexing="ij"))
    return ndimage.map_coordinates(sdf, coords, order=1, mode="nearest")
