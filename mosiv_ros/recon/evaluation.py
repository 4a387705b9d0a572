"""Reconstruction figures against ground truth: per-object Chamfer distance.

In metres and as a fraction of the object's size. What it is for: comparing an
``ObservedFrame``'s per-object points with ground-truth points of the same object (never union
sets), for tests and benchmarks. The Chamfer distance is ``mosiv_ros.metrics``'s; an object's
size is the largest edge of its ground-truth bounding box (a sphere's diameter).
What it is not for: losses inside the identifier (``mosiv_ros.identify`` has its own).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mosiv_ros.metrics import mean_nearest_distance


@dataclass(frozen=True)
class ChamferFigure:
    """Chamfer distance of one object at one stamp.

    ``accuracy`` = mean d(estimate -> truth), ``completeness`` = mean d(truth -> estimate),
    ``chamfer`` their mean, all in metres; ``relative`` = chamfer / object size.
    """

    object_id: int
    stamp_ns: int
    chamfer: float
    accuracy: float
    completeness: float
    relative: float


def object_size(truth: np.ndarray) -> float:
    """Largest edge (m) of the bounding box of an object's ground-truth points."""
    return float(np.max(truth.max(axis=0) - truth.min(axis=0)))


def chamfer_figure(object_id: int, stamp_ns: int, estimate: np.ndarray,
                   truth: np.ndarray) -> ChamferFigure:
    """The ChamferFigure of one object's estimate against its ground truth."""
    accuracy, completeness = mean_nearest_distance(estimate, truth), mean_nearest_distance(truth, estimate)
    cd = (accuracy + completeness) / 2.0
    return ChamferFigure(object_id, stamp_ns, cd, accuracy, completeness, cd / object_size(truth))


def union_of_balls_volume(centres: np.ndarray, radius: float, floor: float | None = None,
                          step: float = 0.001) -> float:
    """Volume (m^3) of the union of balls of ``radius`` around ``centres``, above z = ``floor``.

    The solid a particle-splatting renderer (the synthetic recorder's) shows: what a camera can
    observe of particles, as opposed to the volume they stand for. Counted on a grid of ``step``.
    """
    lo, hi = centres.min(axis=0) - radius, centres.max(axis=0) + radius
    if floor is not None:
        lo[2] = max(lo[2], floor)
    axes = [np.arange(lo[a] + step / 2, hi[a], step) for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    distance, _ = cKDTree(centres).query(grid, distance_upper_bound=radius)
    return float(np.count_nonzero(distance <= radius)) * step**3

