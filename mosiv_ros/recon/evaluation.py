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
