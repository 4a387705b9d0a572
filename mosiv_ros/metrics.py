"""Geometry and image metrics: 3D (CD, EMD) of point sets, 2D (IoU, PSNR, SSIM) of images.

- CD: Chamfer distance in metres, CD(A, B) = (mean_a d(a, B) + mean_b d(b, A)) / 2, the mean of
  the two one-sided mean nearest-neighbour distances (``mean_nearest_distance``);
- EMD: earth mover's distance in metres, the mean distance of the optimal one-to-one matching
  of two equal-size random subsets (``EMD_POINTS`` points each; exact assignment);
- IoU: intersection over union of two silhouettes;
- PSNR (dB) and SSIM (Wang et al. 2004, Gaussian window sigma 1.5, on luminance) of two RGB
  images.

What it is for: every stage that measures how far two point sets or images are apart (the
reconstruction figures, the family choice's held-out error, the loop's residual, the twin's
scores); it depends on numpy and scipy only, so any layer may use it.
What it is not for: the identifier's losses (``identify.losses``), which are squared and carry
gradients.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

EMD_POINTS = 512

__all__ = ["EMD_POINTS", "chamfer_distance", "emd", "iou", "mean_nearest_distance", "psnr", "ssim"]


def mean_nearest_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Mean distance (m) from each point of ``a`` (N, 3) to its nearest in ``b`` (M, 3).

    inf if one is empty.
    """
    if len(a) == 0 or len(b) == 0:
        return float("inf")
    return float(cKDTree(np.asarray(b, dtype=np.float64)).query(np.asarray(a, dtype=np.float64))[0].mean())


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Chamfer distance (m) of two point sets; inf if one is empty."""
    return (mean_nearest_distance(a, b) + mean_nearest_distance(b, a)) / 2.0


def emd(a: np.ndarray, b: np.ndarray, points: int = EMD_POINTS, seed: int = 0) -> float:
    """Earth mover's distance (m) between two point sets, on equal random subsets."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if len(a) == 0 or len(b) == 0:
        return float("inf")
    rng = np.random.default_rng(seed)
    n = min(points, len(a), len(b))
    a = a[rng.choice(len(a), n, replace=False)]
    b = b[rng.choice(len(b), n, replace=False)]
    cost = cdist(a, b)
    rows, cols = linear_sum_assignment(cost)
    return float(cost[rows, cols].mean())


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (1 when both are empty)."""
    a, b = np.asarray(a, dtype=bool), np.asarray(b, dtype=bool)
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio (dB) of two uint8 images (inf when identical)."""
    mse = np.mean((np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Structural similarity of two uint8 RGB (or grey) images, on luminance, in [-1, 1]."""
    a, b = _luminance(a), _luminance(b)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    mu_a, mu_b = gaussian_filter(a, 1.5), gaussian_filter(b, 1.5)
    var_a = gaussian_filter(a * a, 1.5) - mu_a**2
    var_b = gaussian_filter(b * b, 1.5) - mu_b**2
    cov = gaussian_filter(a * b, 1.5) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return float(s.mean())


def _luminance(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image, dtype=np.float64)
    if image.ndim == 3:
        return image @ np.array([0.299, 0.587, 0.114])
    return image
