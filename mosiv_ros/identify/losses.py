"""Per-object geometry losses between simulated particles and observations, with gradients.

MOSIV Sec. "Per-object Geometry Alignment Loss": for every object k only, a symmetric Chamfer
distance between its simulated particles and its observed points, and a silhouette loss
comparing a soft rendering of its particles with its observed mask in each view. Summing these
per object keeps one object's points from "explaining" another's at contact. A scene-level
(union) variant of both exists for the ablation only (``per_object=False``).

- Chamfer: mean squared nearest-neighbour distance in both directions (m^2), nearest neighbours
  by KD-tree; its gradient holds the nearest-neighbour assignment fixed (exact almost
  everywhere).
- Silhouette: each particle is a Gaussian splat of standard deviation ``splat_radius`` (m)
  projected to pixels, the soft mask is A = 1 - prod(1 - 0.9 w_i), and the loss is the mean
  absolute difference to the observed mask over the pixels that show object k or background;
  pixels of other objects are unknown for k (they may occlude it) and left out. Gradients come
  from torch autograd.

What it is for: the identifier's objective. What it is not for: evaluation metrics reported to
users (``mosiv_ros.evaluate``), which use unsquared distances.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from mosiv_ros.identify.observations import View

SPLAT_OPACITY = 0.9


def chamfer(x: np.ndarray, y: np.ndarray, y_tree: cKDTree | None = None) -> tuple[float, np.ndarray]:
    """Symmetric Chamfer (mean squared nearest distances both ways) and dL/dx.

    ``y_tree``: a KD-tree of ``y`` already built (observations are fitted many times).
    """
    if len(x) == 0 or len(y) == 0:
        return 0.0, np.zeros_like(x)
    dist_x, nearest_y = (y_tree or cKDTree(y)).query(x)
    dist_y, nearest_x = cKDTree(x).query(y)
    loss = float(np.mean(dist_x**2) + np.mean(dist_y**2))
    grad = 2.0 * (x - y[nearest_y]) / len(x)
    np.add.at(grad, nearest_x, -2.0 * (y - x[nearest_x]) / len(y))
    return loss, grad


def geometry_loss(x: np.ndarray, object_index: np.ndarray, observed: list[np.ndarray],
                  per_object: bool = True,
                  trees: list[cKDTree | None] | None = None) -> tuple[float, np.ndarray, np.ndarray]:
    """Chamfer loss of one frame: (total, dL/dx (N, 3), per-object losses (K,)).

    ``per_object=False`` is the scene-level ablation: one Chamfer between the union of all
    simulated particles and the union of all observed points (per-object losses then NaN).
    ``trees``: KD-trees of the observed point sets, built once by the caller.
    """
    x = np.asarray(x, dtype=np.float64)
    grad = np.zeros_like(x)
    per = np.full(len(observed), np.nan)
    if not per_object:
        union = np.concatenate([o for o in observed if len(o)] or [np.zeros((0, 3))])
        total, grad = chamfer(x, union)
        return total, grad, per
    total = 0.0
    for k, points in enumerate(observed):
        mine = object_index == k
        if not len(points) or not mine.any():
            continue
        per[k], g = chamfer(x[mine], points, trees[k] if trees else None)
        grad[mine] = g
        total += per[k]
    return total, grad, per


def _soft_mask(uv: torch.Tensor, sigma: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """A = 1 - prod_i (1 - opacity w_i(p)) over pixels p, Gaussian w_i within 3 sigma."""
    reach = int(np.clip(np.ceil(3 * float(sigma.detach().max())), 1, 8))
    offsets = torch.arange(-reach, reach + 1, dtype=uv.dtype, device=uv.device)
    dy, dx = torch.meshgrid(offsets, offsets, indexing="ij")
    base = torch.round(uv.detach())
    px = base[:, None, 0] + dx.reshape(1, -1)
    py = base[:, None, 1] + dy.reshape(1, -1)
    inside = (px >= 0) & (px < width) & (py >= 0) & (py < height)
    d2 = (px - uv[:, None, 0]) ** 2 + (py - uv[:, None, 1]) ** 2
    w = SPLAT_OPACITY * torch.exp(-d2 / (2 * sigma[:, None] ** 2))
    log_clear = torch.log1p(-w)[inside]
    index = (py * width + px)[inside].long()
    total = torch.zeros(height * width, dtype=uv.dtype, device=uv.device).index_add(0, index, log_clear)
    return (1 - torch.exp(total)).reshape(height, width)


def silhouette_loss(x: np.ndarray, object_index: np.ndarray, object_ids: list[int],
                    views: list[View], masks: dict[str, np.ndarray], splat_radius: float,
                    per_object: bool = True, device: str = "cpu") -> tuple[float, np.ndarray]:
    """Silhouette loss of one frame over its views and its gradient dL/dx (N, 3).

    The loss is the mean over views of the sum over objects of the L1 mask difference. The
    soft rendering runs in torch on ``device`` (the simulation's GPU, where there is one).
    """
    views = [v for v in views if v.name in masks]
    if not views:
        return 0.0, np.zeros_like(x)
    xt = torch.tensor(np.asarray(x, dtype=np.float64), requires_grad=True, device=device)
    index = torch.as_tensor(object_index, device=device)
    total = torch.zeros((), dtype=torch.float64, device=device)
    for view in views:
        T = torch.as_tensor(np.linalg.inv(view.T_world_optical), device=device)
        cam = xt @ T[:3, :3].T + T[:3, 3]
        front = cam[:, 2] > 1e-3
        z = torch.where(front, cam[:, 2], torch.ones_like(cam[:, 2]))
        K = torch.as_tensor(view.K, device=device)
        uv = cam[:, :2] / z[:, None] * torch.stack([K[0, 0], K[1, 1]]) + K[:2, 2]
        sigma = torch.clamp(K[0, 0] * splat_radius / z, min=0.5)
        observed = torch.as_tensor(masks[view.name].astype(np.int64), device=device)
        groups = [(k, [object_ids[k]]) for k in range(len(object_ids))] if per_object else [(-1, object_ids)]
        for k, ids in groups:
            chosen = front & ((index == k) if k >= 0 else torch.ones_like(front))
            if not bool(chosen.any()):
                continue
            soft = _soft_mask(uv[chosen], sigma[chosen], view.height, view.width)
            target = torch.isin(observed, torch.as_tensor(ids, device=device)).to(soft.dtype)
            known = (target > 0) | (observed == 0)
            if bool(known.any()):  # all pixels of other objects: nothing to compare here
                total = total + (soft - target).abs()[known].mean()
    if not total.requires_grad:  # no particle in view, or nothing known about it
        return 0.0, np.zeros_like(x)
    total = total / len(views)
    total.backward()
    return float(total.detach()), xt.grad.cpu().numpy()
