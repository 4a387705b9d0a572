"""Per-object geometry losses between simulated particles and observations, with gradients.

MOSIV Sec. "Per-object Geometry Alignment Loss": for every object k only, a symmetric Chamfer
distance between its simulated particles and its observed points, and a silhouette loss
comparing a soft rendering of its particles with its observed mask in each view. Summing these
per object keeps one object's points from "explaining" another's at contact. A scene-level
(union) variant of both exists for the ablation only (``per_object=False``).

- Chamfer: mean squared nearest-neighbour distance in both directions (m^2), nearest neighbours
  by KD-tree; its gradient holds the nearest-neighbour assignment fixed (exact almost
  everywhere).
- Tracks: each surface track attached to its object's particles (``TrackAttachment``) is
  compared with the attached point of the simulated particles, r = sum_j w_j x_j + o - y, by the
  pseudo-Huber s^2 (sqrt(1 + |r|^2 / s^2) - 1) (about |r|^2 / 2 below the scale s, m^2 like the
  Chamfer, growing only as s |r| beyond it, so that a drifted track pulls with a bounded force),
  times the track's confidence, mean over the object's tracks alive in the frame; exact gradient.
- Silhouette: each particle is a Gaussian splat of standard deviation ``splat_radius`` (m)
  projected to pixels, the soft mask is A = 1 - prod(1 - 0.9 w_i), and the loss is the mean
  absolute difference to the observed mask over the pixels that show object k or background;
  pixels of other objects are unknown for k (they may occlude it) and left out. Gradients come
  from torch autograd; all frames of a window are rendered per view in one batch.

What it is for: the identifier's objective. What it is not for: evaluation metrics reported to
users (``mosiv_ros.evaluate``), which use unsquared distances.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import torch
from scipy.spatial import cKDTree

from mosiv_ros.identify.observations import TrackAttachment, View

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


def track_loss(x: np.ndarray, tracks: TrackAttachment, frame: int, scale: float,
               n_objects: int) -> tuple[float, np.ndarray, np.ndarray]:
    """Track loss of one frame: (total, dL/dx (N, 3), per-object losses (K,)).

    ``x`` (N, 3) the simulated particles at ``frame`` of ``tracks``; ``scale`` the pseudo-Huber
    scale s (m). A track not alive in the frame adds nothing, nor does an object without one.
    """
    grad = np.zeros_like(x, dtype=np.float64)
    per = np.zeros(n_objects)
    alive = np.flatnonzero(np.isfinite(tracks.positions[frame, :, 0]))
    if not len(alive):
        return 0.0, grad, per
    weights, particles = tracks.weights[alive], tracks.particles[alive]
    r = tracks.points(x, alive) - tracks.positions[frame, alive]
    root = np.sqrt(1.0 + np.sum(r**2, axis=1) / scale**2)
    objects = tracks.object_index[alive]
    count = np.bincount(objects, minlength=n_objects)
    share = tracks.confidence[frame, alive] / count[objects]  # the mean over the object's tracks
    per = np.bincount(objects, share * scale**2 * (root - 1.0), minlength=n_objects)
    dr = (share / root)[:, None] * r  # d(s^2 (root - 1)) / dr = r / root
    np.add.at(grad, particles, weights[..., None] * dr[:, None, :])
    return float(per.sum()), grad, per


def _soft_masks(uv: torch.Tensor, sigma: torch.Tensor, valid: torch.Tensor, height: int,
                width: int) -> torch.Tensor:
    """(F, H, W) soft masks A = 1 - prod_i (1 - opacity w_i(p)), Gaussian w_i within 3 sigma.

    ``uv`` (F, M, 2) pixel positions, ``sigma`` (F, M) splat radii in pixels, ``valid`` (F, M)
    the particles that count (in front of the camera).
    """
    n_frames = uv.shape[0]
    reach = int(np.clip(np.ceil(3 * float(sigma.detach()[valid].max())), 1, 8))
    offsets = torch.arange(-reach, reach + 1, dtype=uv.dtype, device=uv.device)
    dy, dx = torch.meshgrid(offsets, offsets, indexing="ij")
    base = torch.round(uv.detach())
    px = base[..., 0, None] + dx.reshape(1, 1, -1)
    py = base[..., 1, None] + dy.reshape(1, 1, -1)
    inside = (px >= 0) & (px < width) & (py >= 0) & (py < height) & valid[..., None]
    d2 = (px - uv[..., 0, None]) ** 2 + (py - uv[..., 1, None]) ** 2
    w = SPLAT_OPACITY * torch.exp(-d2 / (2 * sigma[..., None] ** 2))
    log_clear = torch.log1p(-w)[inside]
    frame = torch.arange(n_frames, device=uv.device).reshape(-1, 1, 1)
    index = (frame * (height * width) + py * width + px)[inside].long()
    total = torch.zeros(n_frames * height * width, dtype=uv.dtype, device=uv.device)
    return (1 - torch.exp(total.index_add(0, index, log_clear))).reshape(n_frames, height, width)


@contextmanager
def _torch_threads(device: str):
    """Run torch on one CPU thread (on a CUDA ``device``, change nothing).

    These tensors are small, and a second OpenMP thread spinning for a core that another
    process held made one frame's silhouette 30x slower (1.8 s instead of 0.06 s).
    """
    if device != "cpu":
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


SPLAT_BATCH = {"cpu": 1 << 18, "cuda": 1 << 25}
"""Splat-pixel pairs rendered in one batch: on a CPU about one frame of a few thousand
particles (larger batches fall out of the cache: 20 frames at once took 5x as long as 20 one at
a time), on a GPU every frame of a window (one frame at a time is launch overhead)."""


def silhouette_losses(x: np.ndarray, object_index: np.ndarray, object_ids: list[int],
                      views: list[View], masks: list[dict[str, np.ndarray]], splat_radius: float,
                      per_object: bool = True, device: str = "cpu") -> tuple[float, np.ndarray]:
    """Silhouette loss summed over frames, and its gradient dL/dx (F, N, 3).

    ``x`` (F, N, 3) the particles of each frame, ``masks[f]`` the observed masks of frame f by
    view name. A frame's loss is the mean over its views (those with a mask) of the sum over
    objects of the L1 mask difference on the pixels known for the object; an object with no
    particle in front of a camera adds nothing there. Frames are rendered in batches of up to
    ``SPLAT_BATCH`` splat-pixel pairs, in torch on ``device`` (the simulation's GPU, where
    there is one).
    """
    per, grad = _silhouettes(x, object_index, object_ids, views, masks, splat_radius, per_object,
                             device, grad=True)
    return float(per.sum()), grad


def silhouette_object_losses(x: np.ndarray, object_index: np.ndarray, object_ids: list[int],
                             views: list[View], masks: list[dict[str, np.ndarray]],
                             splat_radius: float, per_object: bool = True,
                             device: str = "cpu") -> np.ndarray:
    """``silhouette_losses`` split by object (K,), without a gradient; (1,) if not ``per_object``."""
    return _silhouettes(x, object_index, object_ids, views, masks, splat_radius, per_object,
                        device, grad=False)[0]


def _silhouettes(x: np.ndarray, object_index: np.ndarray, object_ids: list[int],
                 views: list[View], masks: list[dict[str, np.ndarray]], splat_radius: float,
                 per_object: bool, device: str, grad: bool) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, dtype=np.float64)
    budget = SPLAT_BATCH["cpu" if device == "cpu" else "cuda"]
    step = max(1, budget // (max(x.shape[1], 1) * (2 * 3 + 1) ** 2))  # 3-pixel splats typical
    per, gradient = np.zeros(len(object_ids) if per_object else 1), np.zeros_like(x)
    with _torch_threads(device), torch.set_grad_enabled(grad):
        for first in range(0, len(x), step):
            chunk = slice(first, first + step)
            values, gradient[chunk] = _silhouette_batch(x[chunk], object_index, object_ids, views,
                                                        masks[chunk], splat_radius, per_object,
                                                        device, grad)
            per += values
    return per, gradient


def _silhouette_batch(x: np.ndarray, object_index: np.ndarray, object_ids: list[int],
                      views: list[View], masks: list[dict[str, np.ndarray]], splat_radius: float,
                      per_object: bool, device: str, grad: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per group (each object, or all with the scene-level loss) the loss of frames ``x``; dL/dx."""
    n_frames = len(x)
    counts = np.array([sum(v.name in m for v in views) for m in masks], dtype=np.float64)
    n_groups = len(object_ids) if per_object else 1
    if not counts.any():
        return np.zeros(n_groups), np.zeros_like(x)
    xt = torch.tensor(x, requires_grad=grad, device=device)
    index = torch.as_tensor(object_index, device=device)
    frame_weight = torch.as_tensor(np.divide(1.0, counts, out=np.zeros(n_frames), where=counts > 0),
                                   device=device)
    groups = ([(index == k, [object_ids[k]]) for k in range(len(object_ids))] if per_object
              else [(torch.ones_like(index, dtype=torch.bool), list(object_ids))])
    totals = [torch.zeros((), dtype=torch.float64, device=device) for _ in groups]
    for view in views:
        frames = [f for f in range(n_frames) if view.name in masks[f]]
        if not frames:
            continue
        rows = torch.as_tensor(frames, device=device)
        T = torch.as_tensor(np.linalg.inv(view.T_world_optical), device=device)
        cam = xt[rows] @ T[:3, :3].T + T[:3, 3]
        front = cam[..., 2] > 1e-3
        z = torch.where(front, cam[..., 2], torch.ones_like(cam[..., 2]))
        K = torch.as_tensor(view.K, device=device)
        uv = cam[..., :2] / z[..., None] * torch.stack([K[0, 0], K[1, 1]]) + K[:2, 2]
        sigma = torch.clamp(K[0, 0] * splat_radius / z, min=0.5)
        observed = torch.as_tensor(np.stack([masks[f][view.name] for f in frames]).astype(np.int64),
                                   device=device)
        for g, (mine, ids) in enumerate(groups):
            valid = front[:, mine]
            if not bool(valid.any()):
                continue
            soft = _soft_masks(uv[:, mine], sigma[:, mine], valid, view.height, view.width)
            target = torch.isin(observed, torch.as_tensor(ids, device=device)).to(soft.dtype)
            known = ((target > 0) | (observed == 0)).to(soft.dtype)
            pixels = known.sum(dim=(1, 2))
            # frames where every pixel is another object's, or no particle is in view: nothing
            counted = (pixels > 0) & valid.any(dim=1)
            per_frame = ((soft - target).abs() * known).sum(dim=(1, 2)) / pixels.clamp(min=1)
            totals[g] = totals[g] + (per_frame * counted * frame_weight[rows]).sum()
    values = torch.stack(totals)
    if not values.requires_grad:  # no gradient asked, or no particle in view
        return values.detach().cpu().numpy(), np.zeros_like(x)
    values.sum().backward()
    return values.detach().cpu().numpy(), xt.grad.cpu().numpy()


def silhouette_loss(x: np.ndarray, object_index: np.ndarray, object_ids: list[int],
                    views: list[View], masks: dict[str, np.ndarray], splat_radius: float,
                    per_object: bool = True, device: str = "cpu") -> tuple[float, np.ndarray]:
    """``silhouette_losses`` of one frame: particles ``x`` (N, 3), masks by view name."""
    loss, grad = silhouette_losses(np.asarray(x)[None], object_index, object_ids, views, [masks],
                                   splat_radius, per_object, device)
    return loss, grad[0]
