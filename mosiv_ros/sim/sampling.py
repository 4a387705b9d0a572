"""Particles filling simple solids on a regular lattice: boxes, spheres, cylinders, tori.

For tests, benchmarks and synthetic scenes; lifting observed geometry into particles is stage 2's
job (``mosiv_ros.lifting``). Each function returns positions (N, 3) in metres and the volume of
one particle (spacing^3), so that N * volume approximates the solid's volume.
"""

from __future__ import annotations

import numpy as np


def lattice_counts(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """Cells (3,) along each axis of the lattice ``lattice(lo, hi, spacing)`` fills the box with.

    As floats: a caller can check a lattice too large to allocate (or to count in int64).
    """
    if spacing <= 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    extent = np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)
    return np.maximum(np.round(extent / spacing), 1.0)


def lattice(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """Cell centres of a lattice of ``spacing`` filling the box lo..hi (N, 3)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    counts = lattice_counts(lo, hi, spacing).astype(int)
    start = (lo + hi) / 2 - (counts - 1) * spacing / 2
    axes = [start[a] + spacing * np.arange(counts[a]) for a in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def box(center, half_extents, spacing: float) -> tuple[np.ndarray, float]:
    """A box of ``half_extents`` (3,) around ``center``, axis-aligned."""
    center, half = np.asarray(center, float), np.asarray(half_extents, float)
    return lattice(center - half, center + half, spacing), spacing**3


def sphere(center, radius: float, spacing: float) -> tuple[np.ndarray, float]:
    """A ball of ``radius`` around ``center``."""
    center = np.asarray(center, float)
    x = lattice(center - radius, center + radius, spacing)
    return x[np.linalg.norm(x - center, axis=1) <= radius], spacing**3


def cylinder(center, radius: float, half_height: float, spacing: float) -> tuple[np.ndarray, float]:
    """A cylinder along z of ``radius`` and ``half_height`` around ``center``."""
    center = np.asarray(center, float)
    half = np.array([radius, radius, half_height])
    x = lattice(center - half, center + half, spacing)
    return x[np.linalg.norm(x[:, :2] - center[:2], axis=1) <= radius], spacing**3


def torus(center, major_radius: float, minor_radius: float,
          spacing: float) -> tuple[np.ndarray, float]:
    """A torus in the xy plane around ``center``."""
    center = np.asarray(center, float)
    reach = major_radius + minor_radius
    x = lattice(center - [reach, reach, minor_radius], center + [reach, reach, minor_radius], spacing)
    d = x - center
    ring = np.linalg.norm(d[:, :2], axis=1) - major_radius
    return x[ring**2 + d[:, 2] ** 2 <= minor_radius**2], spacing**3
