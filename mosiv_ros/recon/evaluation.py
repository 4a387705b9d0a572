"""Reconstruction figures against ground truth: per-object Chamfer distance.

In metres and as a fraction of the object's size. What it is for: comparing an
``ObservedFrame``'s per-object points with ground-truth points of the same object (never union
sets), for tests and benchmarks. Chamfer distance here is the mean of
the two one-sided mean nearest-neighbour distances, CD(A, B) = (mean_a d(a, B) + mean_b d(b, A)) / 2;
an object's size is the largest edge of its ground-truth bounding box (a sphere's diameter).
What it is not for: losses inside the identifier (``mosiv_ros.identify`` has its own).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


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


def chamfer(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float, float]:
    """(CD, accuracy, completeness) in metres of two point sets (N, 3), (M, 3); inf if one is empty."""
    if len(estimate) == 0 or len(truth) == 0:
        return float("inf"), float("inf"), float("inf")
    accuracy = float(cKDTree(truth).query(estimate)[0].mean())
    completeness = float(cKDTree(estimate).query(truth)[0].mean())
    return (accuracy + completeness) / 2.0, accuracy, completeness


def object_size(truth: np.ndarray) -> float:
    """Largest edge (m) of the bounding box of an object's ground-truth points."""
    return float(np.max(truth.max(axis=0) - truth.min(axis=0)))


def chamfer_figure(object_id: int, stamp_ns: int, estimate: np.ndarray,
                   truth: np.ndarray) -> ChamferFigure:
    """The ChamferFigure of one object's estimate against its ground truth."""
    cd, accuracy, completeness = chamfer(estimate, truth)
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

