"""Reconstruction figures against ground truth: per-object Chamfer distance, track errors.

In metres and as a fraction of the object's size. What it is for: comparing an
``ObservedFrame``'s per-object points with ground-truth points of the same object (never union
sets), for tests and benchmarks; and how far surface tracks drift from the ground truth's
motion (``track_errors``). The Chamfer distance is ``mosiv_ros.metrics``'s; an object's size is
the largest edge of its ground-truth bounding box (a sphere's diameter).
What it is not for: losses inside the identifier (``mosiv_ros.identify`` has its own).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mosiv_ros.metrics import mean_nearest_distance
from mosiv_ros.recon.tracks import SurfaceTracks


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



NEAREST_TRUTH = 4
"""Ground-truth particles whose mean motion a track's point is compared with."""


def track_errors(tracks: SurfaceTracks, truth: np.ndarray, truth_ids: np.ndarray) -> np.ndarray:
    """(F, T) m: how far each track has moved from where the ground truth moved its point.

    ``truth`` (F, N, 3) holds the ground-truth particles at the tracks' frames, ``truth_ids``
    (N,) their object ids. At a track's first frame it is attached to the NEAREST_TRUTH nearest
    particles of its object; at every later frame its error is the distance between its
    displacement since then and their mean displacement (so the gap between a visible surface
    and the particle centres under it does not count). NaN where the track is not alive; 0 at
    its first frame.
    """
    frames, count = tracks.positions.shape[:2]
    errors = np.full((frames, count), np.nan)
    alive = tracks.alive
    born = np.argmax(alive, axis=0)
    for start in np.unique(born[alive.any(axis=0)]):
        for object_id in np.unique(tracks.object_id):
            mine = np.flatnonzero((born == start) & (tracks.object_id == object_id) & alive[start])
            particles = np.flatnonzero(truth_ids == object_id)
            if len(mine) == 0 or len(particles) == 0:
                continue
            k = min(NEAREST_TRUTH, len(particles))
            nearest = particles[cKDTree(truth[start, particles]).query(tracks.positions[start, mine], k=k)[1]]
            nearest = nearest.reshape(len(mine), k)
            moved = truth[:, nearest].mean(axis=2) - truth[start, nearest].mean(axis=1)
            tracked = tracks.positions[:, mine] - tracks.positions[start, mine]
            errors[start:, mine] = np.linalg.norm(tracked - moved, axis=2)[start:]
    return errors
