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
- Silhouette: each particle is a Gaussian splat of standard deviation ``splat_radius`` (m; one
  for all objects, or one per object, as ``calibrated_splat_radius`` gives them)
  projected to pixels, the soft mask is A = 1 - prod(1 - 0.9 w_i), and the loss is the mean
  absolute difference to the observed mask over the pixels that show object k or background;
  pixels of other objects are unknown for k (they may occlude it) and left out. The splats are
  summed (as logs) and differentiated by a Warp kernel, the rest by torch autograd; all views,
  objects and frames of a window are rendered in one batch.

Two forms of the same terms: per frame in numpy on the CPU (``geometry_loss``, ``track_loss``,
``silhouette_losses``: KD-trees, the silhouettes in torch a batch of frames at a time), and as
torch tensors on one device for many rows (parameter sets) and frames at once
(``tensor_terms``: exact nearest neighbours by ``nearest``, gradients through torch's autograd,
the Chamfer's and the splats' written out), which the identifier uses on a GPU. The two agree
to float64 rounding, but for which of several equally near neighbours takes a tie.

What it is for: the identifier's objective. What it is not for: evaluation metrics reported to
users (``mosiv_ros.evaluate``), which use unsquared distances.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, fields

import numpy as np
import torch
import warp as wp
from scipy.spatial import cKDTree

from mosiv_ros.config import LossConfig
from mosiv_ros.identify.observations import MaskTensors, ObservedTensors, TrackAttachment, TrackTensors, View
from mosiv_ros.sim.runtime import load_modules, resolve_device

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


NEAREST_BLOCK = (16, 128)
"""Least and most targets in a block of ``nearest``'s search. A query costs one box bound per
block and an exhaustive search of the few blocks near it; about sqrt(M) / 2 targets a block (M
the targets) kept that lowest on elastic_on_plastic (a clay particle: 240 bounds and 650
distances, not 15,000 distances, to the clay's 15,000 observed points)."""


_SPREAD: dict[torch.device, torch.Tensor] = {}
"""By device, (1024,) each 10-bit value with its bits moved to every third bit (bit b to 3 b)."""


def _spread_bits(device: torch.device) -> torch.Tensor:
    """``_SPREAD`` on ``device``, made there once (an upload waits for the device)."""
    if device not in _SPREAD:
        values = np.arange(1024, dtype=np.int64)
        _SPREAD[device] = torch.as_tensor(sum(((values >> b) & 1) << (3 * b) for b in range(10)), device=device)
    return _SPREAD[device]


def _morton(points: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(J, M) Z-order keys of points (J, M, 3), invalid points last.

    On a 1024^3 lattice over the bounding box of each job's valid points; each axis's cell
    spread to every third bit by a table (``_SPREAD``), x lowest.
    """
    lo = torch.where(valid[..., None], points, math.inf).amin(dim=1, keepdim=True)
    hi = torch.where(valid[..., None], points, -math.inf).amax(dim=1, keepdim=True)
    scaled = (points - lo) / (hi - lo).clamp(min=1e-12) * 1023
    cell = torch.where(valid[..., None], scaled, 0.0).clamp(0, 1023).long()
    spread = _spread_bits(points.device)[cell]
    key = spread[..., 0] | (spread[..., 1] << 1) | (spread[..., 2] << 2)
    return torch.where(valid, key, 1 << 31)


@dataclass
class TargetBlocks:
    """Each job's targets sorted along a Z-order curve into blocks of S (``NEAREST_BLOCK``).

    ``points`` (J, B, S, 3), which are valid (J, B, S), their indices in the targets given
    (``order``, J, B, S), each block's bounding box, lower and upper corner (J, B, 3) (+inf
    and -inf for a block without a valid point), and the centroid of its valid points (J, B, 3)
    (1e100 without). Built once for targets that do not change (the observed points,
    ``ObservedTensors.blocks``) and taken by any queries after (``nearest``).
    """

    points: torch.Tensor
    valid: torch.Tensor
    order: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    centroid: torch.Tensor

    @classmethod
    def of(cls, targets: torch.Tensor, valid: torch.Tensor) -> TargetBlocks:
        """The blocks of targets (J, M, 3) of which ``valid`` (J, M) are points."""
        n_jobs, m = valid.shape
        least, most = NEAREST_BLOCK
        size = int(np.clip(2 ** round(math.log2(max(math.sqrt(m) / 2, 1))), least, most))
        blocks = max(1, -(-m // size))
        extra = blocks * size - m
        targets = torch.cat([targets, targets.new_zeros((n_jobs, extra, 3))], dim=1)
        valid = torch.cat([valid, valid.new_zeros((n_jobs, extra))], dim=1)
        order = _morton(targets, valid).argsort(dim=1, stable=True)
        points = targets.gather(1, order[..., None].expand(-1, -1, 3)).view(n_jobs, blocks, size, 3)
        valid = valid.gather(1, order).view(n_jobs, blocks, size)
        lo = torch.where(valid[..., None], points, math.inf).amin(dim=2)
        hi = torch.where(valid[..., None], points, -math.inf).amax(dim=2)
        count = valid.sum(dim=2, keepdim=True)
        centroid = torch.where(count > 0, torch.where(valid[..., None], points, 0.0).sum(dim=2)
                               / count.clamp(min=1), 1e100)
        return cls(points, valid, order.view(n_jobs, blocks, size), lo, hi, centroid)

    def jobs(self, index: slice) -> TargetBlocks:
        """The blocks of jobs ``index`` (views, not copies)."""
        return TargetBlocks(*(getattr(self, f.name)[index] for f in fields(self)))


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    return __dadd_rn(__dadd_rn(__dmul_rn(d[0], d[0]), __dmul_rn(d[1], d[1])), __dmul_rn(d[2], d[2]));
#else
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    return (d[0] * d[0] + d[1] * d[1]) + d[2] * d[2];
#endif
""")
def _rounded_squared(d: wp.vec3d) -> wp.float64:
    """(dx dx + dy dy) + dz dz with every product and sum rounded on its own, as the KD-tree sums.

    Spelled out because a compiler may fuse a product into the next sum (a fused multiply-add,
    rounded once), which can break a tie the KD-tree and the torch sums see.
    """
    ...


@wp.func
def _box_bound(q: wp.vec3d, lo: wp.vec3d, hi: wp.vec3d):
    """Squared distance of ``q`` to the box [lo, hi], summed as ``_rounded_squared``.

    At most any point's in the box (rounding is monotone); inf for an empty block (lo +inf,
    hi -inf).
    """
    zero = wp.float64(0.0)
    gap = wp.vec3d(wp.max(wp.max(lo[0] - q[0], q[0] - hi[0]), zero),
                   wp.max(wp.max(lo[1] - q[1], q[1] - hi[1]), zero),
                   wp.max(wp.max(lo[2] - q[2], q[2] - hi[2]), zero))
    return _rounded_squared(gap)


@wp.kernel(enable_backward=False)
def _nearest_in_blocks(queries: wp.array2d(dtype=wp.vec3d), query_valid: wp.array2d(dtype=wp.uint8),
                       points: wp.array3d(dtype=wp.vec3d), point_valid: wp.array3d(dtype=wp.uint8),
                       order: wp.array3d(dtype=wp.int64), lo: wp.array2d(dtype=wp.vec3d),
                       hi: wp.array2d(dtype=wp.vec3d), centroid: wp.array2d(dtype=wp.vec3d),
                       best: wp.array2d(dtype=wp.float64), index: wp.array2d(dtype=wp.int64)):
    """One thread per (job, query): ``nearest``'s search (its docstring), -1 where nothing was found.

    Query job j searches target job j % (the target jobs), so that targets shared by several
    rows of queries are held once.
    """
    q_job, i = wp.tid()
    j = q_job % points.shape[0]
    found = wp.int32(0)
    near = wp.float64(0.0)
    lowest = wp.int64(-1)
    if query_valid[q_job, i] != wp.uint8(0):
        q = queries[q_job, i]
        blocks = points.shape[1]
        first = wp.int32(0)
        closest = wp.float64(0.0)
        for b in range(blocks):  # the block of nearest centroid: a choice, so any sum will do
            c = wp.length_sq(q - centroid[j, b])
            if b == 0 or c < closest:
                closest = c
                first = b
        for k in range(blocks + 1):  # that block first, then every other one its box does not rule out
            b = first
            if k > 0:
                b = k - 1
            if k == 0 or (b != first and (found == 0 or _box_bound(q, lo[j, b], hi[j, b]) <= near)):
                for s in range(points.shape[2]):
                    if point_valid[j, b, s] != wp.uint8(0):
                        d = _rounded_squared(q - points[j, b, s])
                        t = order[j, b, s]
                        if found == 0 or d < near or (d == near and t < lowest):
                            found = 1
                            near = d
                            lowest = t
    best[q_job, i] = near
    index[q_job, i] = lowest


def _launch(kernel: wp.Kernel, dim: tuple[int, ...], device: torch.device,
            arguments: Callable[[], list]) -> None:
    """Launch one of this module's kernels on the tensors' ``device`` (in torch's stream on a GPU).

    ``arguments()`` gives the kernel's arguments once Warp is loaded (``wp.from_torch`` needs it).
    """
    where = resolve_device("cpu" if device.type == "cpu" else f"cuda:{device.index or 0}")
    load_modules(where, [__name__])
    args = arguments()
    if device.type == "cpu":
        wp.launch(kernel, dim=dim, inputs=args, device=where)
    else:
        with wp.ScopedStream(wp.stream_from_torch(device)):
            wp.launch(kernel, dim=dim, inputs=args, device=where)


def nearest(queries: torch.Tensor, query_valid: torch.Tensor,
            targets: TargetBlocks) -> tuple[torch.Tensor, torch.Tensor]:
    """The exact nearest valid target of each valid query, for J jobs at once, on their device.

    ``queries`` (J, N, 3) float64, which are points ``query_valid`` (J, N) (the rest is
    padding), and the targets sorted into blocks (``TargetBlocks``) of J / R jobs: query job j
    searches target job j % (J / R) (R rows of queries against the same targets, rows outer).
    Returns the squared distance (J, N) and the index among its job's targets (J, N) of each
    query's nearest target: the lowest index
    among equally near ones (a KD-tree takes any of them); inf and -1 for an invalid query or a
    job without a valid target. Distances are summed as the KD-tree sums them, (dx^2 + dy^2) +
    dz^2, each product and sum rounded on its own, so that the two find equally near targets.

    The targets are sorted into blocks along a Z-order curve (``TargetBlocks``). One thread per
    query (a Warp kernel on the tensors' device, in torch's stream) searches the block whose
    centroid is nearest to it exhaustively, then every other block whose bounding box is no
    farther than the nearest target found so far. The box distances are rounded down as the point
    distances are (both are the same sums of monotone roundings), so no block that holds the
    nearest target, or one as near with a lower index, is skipped.
    """
    n_jobs, n = query_valid.shape
    device = queries.device
    target_jobs = targets.valid.shape[0]
    if n_jobs and (not target_jobs or n_jobs % target_jobs):
        raise ValueError(f"{n_jobs} query jobs are no whole number of rows of {target_jobs} target jobs")
    best = torch.empty((n_jobs, n), dtype=torch.float64, device=device)
    index = torch.empty((n_jobs, n), dtype=torch.long, device=device)
    if n_jobs and n:
        _launch(_nearest_in_blocks, (n_jobs, n), device, lambda: [
                wp.from_torch(queries.contiguous(), dtype=wp.vec3d),
                wp.from_torch(query_valid.to(torch.uint8).contiguous()),
                wp.from_torch(targets.points.contiguous(), dtype=wp.vec3d),
                wp.from_torch(targets.valid.to(torch.uint8).contiguous()),
                wp.from_torch(targets.order.contiguous()), wp.from_torch(targets.lo.contiguous(), dtype=wp.vec3d),
                wp.from_torch(targets.hi.contiguous(), dtype=wp.vec3d),
                wp.from_torch(targets.centroid.contiguous(), dtype=wp.vec3d),
                wp.from_torch(best), wp.from_torch(index)])
    return torch.where(index >= 0, best, math.inf), index


def _take(points: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(J, N, 3) the points (J, M, 3) at ``index`` (J, N) (the first one where -1)."""
    return points.gather(1, index.clamp(min=0)[..., None].expand(-1, -1, 3))


def chamfer_batch(x: torch.Tensor, x_valid: torch.Tensor, y: torch.Tensor,
                  y_valid: torch.Tensor, y_blocks: TargetBlocks | None = None) -> torch.Tensor:
    """``chamfer`` of J pairs of point sets as tensors, on their device: (J,) values.

    ``x`` (J, N, 3) and ``y`` (J, M, 3) float64 (N, M >= 1), padded, with which entries are
    points ``x_valid`` (J, N) and ``y_valid`` (J, M); ``y_blocks`` the ``y`` sorted into blocks
    if they are at hand (built here if not). The values are differentiable in ``x``
    (``_Chamfer``), each nearest neighbour held fixed as ``chamfer``'s gradient holds it; 0
    where either set is empty. Nearest neighbours by ``nearest``.
    """
    return _Chamfer.apply(x, x_valid, y, y_valid, y_blocks or TargetBlocks.of(y, y_valid))


class _Chamfer(torch.autograd.Function):
    """``chamfer_batch``: the squared distances are ``nearest``'s, the gradient written out.

    d/dx_i of |x_i - y_nn(i)|^2 is 2 (x_i - y_nn(i)); of |y_k - x_nn(k)|^2, -2 (y_k - x_nn(k)),
    added to the x_nn(k) it holds; the products run in the order autograd takes through the
    distances' sums (dx dx + dy dy) + dz dz, so the bits are autograd's.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor, x_valid: torch.Tensor, y: torch.Tensor, y_valid: torch.Tensor,
                y_blocks: TargetBlocks) -> torch.Tensor:
        x = x.detach()
        there, to_y = nearest(x, x_valid, y_blocks)
        back, to_x = nearest(y, y_valid, TargetBlocks.of(x, x_valid))
        nx, ny = x_valid.sum(dim=1), y_valid.sum(dim=1)
        both = ((nx > 0) & (ny > 0))[:, None]
        x_on, y_on = x_valid & both, y_valid & both
        nx, ny = nx.clamp(min=1), ny.clamp(min=1)
        ctx.save_for_backward(x, y, to_y, to_x, x_on, y_on, nx, ny)
        return torch.where(x_on, there, 0.0).sum(dim=1) / nx + torch.where(y_on, back, 0.0).sum(dim=1) / ny

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x, y, to_y, to_x, x_on, y_on, nx, ny = ctx.saved_tensors
        there = torch.where(x_on[..., None], (grad / nx)[:, None, None] * (x - _take(y, to_y)) * 2, 0.0)
        back = torch.where(y_on[..., None], (grad / ny)[:, None, None] * (y - _take(x, to_x)) * 2, 0.0)
        grad_x = there + torch.zeros_like(x).scatter_add(1, to_x.clamp(min=0)[..., None].expand(-1, -1, 3), -back)
        return grad_x, None, None, None, None


def _chamfer_rows(x: torch.Tensor, visible: torch.Tensor, observed: ObservedTensors, k: int,
                  frames: slice) -> tuple[torch.Tensor, torch.Tensor]:
    """Chamfer of each row's particles against each frame's points: values and which scored.

    ``x`` (R, F, N, 3) the particles (those ``visible`` (R, N) of each row) at ``frames`` of
    ``observed``; against object ``k``'s points there (-1: every object's, the scene-level
    loss). Returns the values (R, F) and whether both sets had points (R, F).
    """
    rows, n_frames, n = x.shape[:3]
    y, y_valid = ((observed.union, observed.union_valid) if k < 0
                  else (observed.points[k], observed.valid[k]))
    if k not in observed.blocks:  # the observed points of every frame, sorted once
        observed.blocks[k] = TargetBlocks.of(y, y_valid)
    y, y_valid = y[frames], y_valid[frames]
    x_valid = visible[:, None].expand(rows, n_frames, n).reshape(rows * n_frames, n)
    y_valid = y_valid.expand(rows, *y_valid.shape).reshape(rows * n_frames, -1)
    values = chamfer_batch(x.reshape(rows * n_frames, n, 3), x_valid,
                           y.expand(rows, *y.shape).reshape(rows * n_frames, -1, 3), y_valid,
                           observed.blocks[k].jobs(frames))
    return values.view(rows, n_frames), (x_valid.any(dim=1) & y_valid.any(dim=1)).view(rows, n_frames)


def track_terms(x: torch.Tensor, tracks: TrackTensors, frames: slice, scale: float,
                n_objects: int) -> torch.Tensor:
    """``track_loss`` of R rows over F frames as tensors: each object's (R, F, K).

    ``x`` (R, F, N, 3) the particles at ``frames`` of ``tracks``; differentiable in ``x``.
    """
    alive = tracks.alive[frames]
    points = (tracks.weights[..., None] * x[:, :, tracks.particles]).sum(dim=3) + tracks.offset
    r = points - tracks.positions[frames]
    root = torch.sqrt(1.0 + (r**2).sum(dim=-1) / scale**2)
    objects = torch.nn.functional.one_hot(tracks.object_index, n_objects).to(x.dtype)  # (T, K)
    count = (alive.to(x.dtype) @ objects) @ objects.T  # (F, T): alive tracks of each one's object
    share = torch.where(alive, tracks.confidence[frames] / count.clamp(min=1), 0.0)
    return (share * scale**2 * (root - 1.0)) @ objects


def _uploaded(values: object, device: torch.device, dtype: torch.dtype | None = None) -> torch.Tensor:
    """Host ``values`` (array-like) as a tensor on ``device``, the copy queued without waiting for the device.

    torch copies from pageable host memory only once the device's queued work is done; from
    page-locked memory it queues the copy. The loss's terms rely on it to be queued behind the
    rollout that computes their particles (``tensor_terms``).
    """
    values = torch.tensor(np.asarray(values), dtype=dtype)  # a copy: the caller's array may change
    return values if device.type == "cpu" else values.pin_memory().to(device, non_blocking=True)


def queued_positions(positions: wp.array, rows: int, particles: int, device: str) -> torch.Tensor:
    """(R, F, N, 3) float64 on ``device``: a queued rollout's positions (``Simulator.queue_rollout``) less frame 0.

    ``positions`` ((F + 1) R N,) ``wp.vec3`` on the same device. On a GPU torch's stream is
    made to wait for the simulator's first, so nothing here waits for the device. Non-finite
    values (a rollout that diverged, which its wait then reports) become 0, so that the terms
    queued behind it stay in bounds.
    """
    if device != "cpu":
        wp.stream_from_torch(torch.device(device)).wait_stream(wp.get_stream(positions.device))
    frames = positions.shape[0] // (rows * particles)
    x = wp.to_torch(positions).view(frames, rows, particles, 3)[1:].transpose(0, 1)
    return torch.nan_to_num(x.to(torch.float64, memory_format=torch.contiguous_format), 0.0, 0.0, 0.0)


def queued_gradient(dx: torch.Tensor, device: str) -> wp.array:
    """dL/dx (R, F, N, 3) as ``Simulator.backward`` takes it on the device: ((F + 1) R N,) ``wp.vec3``, frame 0 zero.

    On a GPU the simulator's stream is made to wait for torch's, which computes it.
    """
    rows, frames, particles = dx.shape[:3]
    out = dx.new_zeros((frames + 1, rows, particles, 3), dtype=torch.float32)
    out[1:] = dx.transpose(0, 1)
    gradient = wp.from_torch(out.view(-1, 3), dtype=wp.vec3)
    if device != "cpu":
        wp.get_stream(gradient.device).wait_stream(wp.stream_from_torch(torch.device(device)))
    return gradient


@dataclass
class Terms:
    """The loss terms of R rows (parameter sets) over F frames, as tensors.

    ``chamfer`` (R, F, K) each object's Chamfer per frame, NaN where it is not scored (no
    observed point or no particle; every object with the scene-level loss); ``chamfer_total``
    (R, F) each frame's Chamfer (the objects' sum, or the scene-level one); ``track`` (R, F, K)
    each object's track loss; ``silhouette`` (R, G) summed over the frames (G = K, or 1 with the
    scene-level loss). A term whose weight is 0, or without its data, is zeros. Differentiable in
    the particles.
    """

    chamfer: torch.Tensor
    chamfer_total: torch.Tensor
    track: torch.Tensor
    silhouette: torch.Tensor


def tensor_terms(x: torch.Tensor, inside: np.ndarray, object_index: np.ndarray,
                 observed: ObservedTensors, object_ids: list[int], frames: slice, loss: LossConfig,
                 splat_radius: float | np.ndarray) -> Terms:
    """Every loss term of R rows of particles at once, on the particles' device.

    ``x`` (R, F, N, 3) float64 the particles at ``frames`` of ``observed``; ``inside`` (R, N)
    on the host, those inside each row's surface, which the Chamfer and silhouette terms score
    (the track term reads every particle); ``object_index`` (N,) each one's object. The same
    terms as ``geometry_loss``, ``silhouette_losses`` and ``track_loss`` (to float64 rounding; a
    nearest neighbour tie may be broken otherwise) for every row and frame, without a KD-tree or
    a round trip to the host per frame. Nothing here waits for the device, so that on a GPU the
    terms can be queued behind the rollout that computes ``x`` (``identify.fit``).
    """
    rows, n_frames = x.shape[:2]
    visible = _uploaded(inside, x.device)
    n_objects = len(object_ids)
    zeros = x.new_zeros((rows, n_frames, n_objects))
    chamfer = torch.full_like(zeros, math.nan)
    if loss.per_object:
        total = zeros[..., 0]
        for k in range(n_objects):
            mine = _uploaded(np.flatnonzero(object_index == k), x.device)
            if len(mine):
                values, scored = _chamfer_rows(x[:, :, mine], visible[:, mine], observed, k, frames)
                chamfer[..., k] = torch.where(scored, values, math.nan)
                total = total + torch.where(scored, values, 0.0)
    else:
        total = _chamfer_rows(x, visible, observed, -1, frames)[0]
    track = zeros
    if loss.track_weight > 0 and observed.tracks is not None:
        track = track_terms(x, observed.tracks, frames, loss.track_scale, n_objects)
    silhouette = x.new_zeros((rows, n_objects if loss.per_object else 1))
    if loss.silhouette_weight > 0 and observed.masks is not None:
        shown = np.arange(len(observed.masks.frame_weight))[frames]
        pixels = observed.masks.pixels(n_objects if loss.per_object else 1)
        for chunk, part in _splat_chunks(inside.sum(axis=1).tolist(), n_frames, str(x.device), pixels):
            chunk = _uploaded(chunk, x.device)  # indexing by a list would upload it and wait
            silhouette = silhouette.index_add(0, chunk, _silhouette_batch(
                x[chunk, part], visible[chunk], object_index, object_ids, observed.masks, shown[part],
                splat_radius, loss.per_object))
    return Terms(chamfer, total, track, silhouette)


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    return log1p(x);
#else
    return __builtin_log1p(x);
#endif
""")
def _log1p(x: wp.float64) -> wp.float64:
    """log(1 + x), accurate near x = 0 (C's and CUDA's ``log1p``)."""
    ...


@wp.func
def _splat_weight(d2: wp.float64, sigma: wp.float64, opacity: wp.float64) -> wp.float64:
    """The opacity-scaled Gaussian weight of a pixel at squared distance ``d2`` from a splat.

    ``opacity`` (``SPLAT_OPACITY``) comes as an argument: a float constant in a kernel is a
    float32, and 0.9 is not one exactly.
    """
    return opacity * wp.exp(-d2 / (wp.float64(2.0) * sigma * sigma))


@wp.kernel(enable_backward=False)
def _splats(uv: wp.array2d(dtype=wp.vec2d), sigma: wp.array2d(dtype=wp.float64), valid: wp.array2d(dtype=wp.uint8),
            group: wp.array(dtype=wp.int32), groups: int, reach: wp.array(dtype=wp.int32),
            height: wp.array(dtype=wp.int32), width: wp.array(dtype=wp.int32), opacity: wp.float64,
            adjoint: int, total: wp.array2d(dtype=wp.float64), adj_uv: wp.array2d(dtype=wp.vec2d),
            adj_sigma: wp.array2d(dtype=wp.float64)):
    """One thread per (image of splats, splat), over the pixels of its footprint (``_SplatSum``).

    Splat m of splat image i renders into image i G + group[m] (G = ``groups``), of
    ``height[i]`` x ``width[i]`` pixels (row-major, at the start of its row of ``total``). The
    footprint: the (2 r + 1)^2 pixels around the splat's rounded centre, rows outer, with r the
    image's ``reach``. Forward (``adjoint`` 0): adds log(1 - w) to each of them in ``total`` (on
    the CPU the threads and their pixels add in that order, so each image's sums are those of
    its splats alone). Adjoint (1): ``total`` holds the gradient of the sums; writes the
    splat's. With l = log(1 - w), w = opacity exp(-d2 / (2 sigma^2)) and d2 = (px - u)^2 +
    (py - v)^2: dl/dw = -1 / (1 - w), dw/du = w (px - u) / sigma^2, dw/dsigma = w d2 / sigma^3.
    """
    i, m = wp.tid()
    if valid[i, m] == wp.uint8(0):
        return
    image = i * groups + int(group[m])
    r = int(reach[image])
    h = int(height[i])
    w_px = int(width[i])
    c = uv[i, m]
    s = sigma[i, m]
    bx = int(wp.rint(c[0]))
    by = int(wp.rint(c[1]))
    g_u = wp.float64(0.0)
    g_v = wp.float64(0.0)
    g_s = wp.float64(0.0)
    for a in range(-r, r + 1):
        py = by + a
        if py >= 0 and py < h:
            for b in range(-r, r + 1):
                px = bx + b
                if px >= 0 and px < w_px:
                    dx = wp.float64(px) - c[0]
                    dy = wp.float64(py) - c[1]
                    d2 = dx * dx + dy * dy
                    w = _splat_weight(d2, s, opacity)
                    if adjoint == 0:
                        wp.atomic_add(total, image, py * w_px + px, _log1p(-w))
                    else:
                        g = -total[image, py * w_px + px] / (wp.float64(1.0) - w) * w / (s * s)
                        g_u += g * dx
                        g_v += g * dy
                        g_s += g * d2 / s
    if adjoint != 0:
        adj_uv[i, m] = wp.vec2d(g_u, g_v)
        adj_sigma[i, m] = g_s


@dataclass(frozen=True)
class _Canvas:
    """Where ``_splats`` renders, as integer tensors (int32) on the splats' device.

    Splat m of splat image i goes into image i G + ``group[m]`` (G = ``groups``; the images are
    (I G, ``stride``)) of ``height[i]`` x ``width[i]`` pixels, reaching ``reach[i G + g]``
    pixels either way.
    """

    group: torch.Tensor
    groups: int
    reach: torch.Tensor
    height: torch.Tensor
    width: torch.Tensor
    stride: int


class _SplatSum(torch.autograd.Function):
    """Per image the sum over splats of log(1 - w) at each pixel, (I G, stride), by ``_splats``."""

    @staticmethod
    def forward(ctx, uv: torch.Tensor, sigma: torch.Tensor, valid: torch.Tensor, canvas: _Canvas) -> torch.Tensor:
        # detached: Warp reads the values only (the gradient is ``backward``'s)
        uv, sigma = uv.detach().contiguous(), sigma.detach().contiguous()
        valid = valid.to(torch.uint8).contiguous()
        total = uv.new_zeros((uv.shape[0] * canvas.groups, canvas.stride))
        ctx.save_for_backward(uv, sigma, valid)
        ctx.canvas = canvas
        _SplatSum.launch((uv, sigma, valid), canvas, 0, total, uv.new_empty((0, 0, 2)), sigma.new_empty((0, 0)))
        return total

    @staticmethod
    def backward(ctx, adj_total: torch.Tensor):
        uv, sigma, valid = ctx.saved_tensors
        adj_uv, adj_sigma = torch.zeros_like(uv), torch.zeros_like(sigma)
        _SplatSum.launch((uv, sigma, valid), ctx.canvas, 1, adj_total.contiguous(), adj_uv, adj_sigma)
        return adj_uv, adj_sigma, None, None

    @staticmethod
    def launch(splats: tuple[torch.Tensor, ...], canvas: _Canvas, adjoint: int, total: torch.Tensor,
               adj_uv: torch.Tensor, adj_sigma: torch.Tensor) -> None:
        """``_splats`` over ``splats`` (uv, sigma, valid) onto ``canvas`` (none: no launch)."""
        uv, sigma, valid = splats
        if uv.shape[0] and uv.shape[1] and total.numel():
            _launch(_splats, tuple(valid.shape), uv.device, lambda: [
                wp.from_torch(uv, dtype=wp.vec2d), wp.from_torch(sigma), wp.from_torch(valid),
                wp.from_torch(canvas.group), canvas.groups, wp.from_torch(canvas.reach),
                wp.from_torch(canvas.height), wp.from_torch(canvas.width), SPLAT_OPACITY, adjoint,
                wp.from_torch(total), wp.from_torch(adj_uv, dtype=wp.vec2d), wp.from_torch(adj_sigma)])


def _soft_masks(uv: torch.Tensor, sigma: torch.Tensor, valid: torch.Tensor, reach: int, height: int,
                width: int) -> torch.Tensor:
    """(I, H, W) soft masks A = 1 - prod_i (1 - opacity w_i(p)) of I images, Gaussian w_i.

    ``uv`` (I, M, 2) pixel positions, ``sigma`` (I, M) splat radii in pixels, ``valid`` (I, M)
    the particles that count (in front of the camera), ``reach`` the pixels a splat reaches
    either way (3 sigma, ``_reach``). The product is a sum of logs that a Warp kernel adds up
    and differentiates (``_SplatSum``; ``_silhouette_batch`` renders many views and objects at
    once the same way): one launch whatever the splats, no splat-pixel tensors.
    """
    device, images = uv.device, uv.shape[0]
    canvas = _Canvas(torch.zeros(uv.shape[1], dtype=torch.int32, device=device), 1,
                     torch.full((images,), reach, dtype=torch.int32, device=device),
                     torch.full((images,), height, dtype=torch.int32, device=device),
                     torch.full((images,), width, dtype=torch.int32, device=device), height * width)
    total = _SplatSum.apply(uv.to(torch.float64), sigma.to(torch.float64), valid, canvas)
    return -torch.expm1(total).reshape(images, height, width)


def _reach(sigma: torch.Tensor) -> torch.Tensor:
    """The pixels splats of radii ``sigma`` reach either way: 3 sigma rounded up, 1 to 8; 0 for -inf (none)."""
    return torch.where(sigma > -math.inf, torch.clamp(torch.ceil(3 * sigma), 1, 8), 0.0).to(torch.int32)


@contextmanager
def torch_threads(device: str):
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
"""Splat-pixel pairs rendered in one batch, per view: on a CPU about one frame of a few
thousand particles, on a GPU every frame of a window (one frame at a time is launch overhead).
The batches also decide which frames share a splat reach (that of the largest of an object's
splats in a view over a row's batch, ``_splat_chunks``), and with it the loss's last digits."""
SPLAT_PIXELS = {"cpu": 1 << 23, "cuda": 1 << 26}
"""Image pixels rendered in one batch (every view's, for each object): each tensor of a batch's
images is 8 bytes a pixel (64 MiB on a CPU, 512 MiB on a GPU), and a batch holds a few at once.
At the sample bags' 96 x 72 pixels ``SPLAT_BATCH`` binds first; at a camera's 1280 x 720 this does."""


def _splat_chunks(counts: list[int], n_frames: int, device: str, pixels: int) -> list[tuple[list[int], slice]]:
    """The (rows, frames) rendered together, each within ``SPLAT_BATCH`` and ``SPLAT_PIXELS``.

    ``counts`` the particles each row renders, ``pixels`` the image pixels a row renders a
    frame (over the views, for each group of objects). A row whose frames fit a batch is
    rendered whole, with as many such rows as fit; another row alone, a batch of frames at a
    time. A row is cut the same way whatever rows share its batches, so that its loss does not
    depend on them (a splat's reach is set by the largest of its row's batch,
    ``_silhouette_batch``).
    """
    kind = "cpu" if device == "cpu" else "cuda"
    most = SPLAT_PIXELS[kind] // max(pixels, 1)
    steps = [max(1, min(SPLAT_BATCH[kind] // (max(n, 1) * (2 * 3 + 1) ** 2), most))  # 3-pixel splats typical
             for n in counts]
    whole = [r for r, step in enumerate(steps) if n_frames <= step]
    together = min([steps[r] for r in whole], default=0) // max(n_frames, 1)
    return ([(whole[i:i + together], slice(None)) for i in range(0, len(whole), max(together, 1))]
            + [([r], slice(f, f + step)) for r, step in enumerate(steps) if n_frames > step
               for f in range(0, n_frames, step)])


def silhouette_losses(x: np.ndarray, object_index: np.ndarray, object_ids: list[int],
                      views: list[View], masks: list[dict[str, np.ndarray]], splat_radius: float | np.ndarray,
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
                             splat_radius: float | np.ndarray, per_object: bool = True,
                             device: str = "cpu") -> np.ndarray:
    """``silhouette_losses`` split by object (K,), without a gradient; (1,) if not ``per_object``."""
    return _silhouettes(x, object_index, object_ids, views, masks, splat_radius, per_object,
                        device, grad=False)[0]


def _silhouettes(x: np.ndarray, object_index: np.ndarray, object_ids: list[int],
                 views: list[View], masks: list[dict[str, np.ndarray]], splat_radius: float | np.ndarray,
                 per_object: bool, device: str, grad: bool) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, dtype=np.float64)
    tensors = MaskTensors.of(views, masks, device)
    per, gradient = np.zeros(len(object_ids) if per_object else 1), np.zeros_like(x)
    with torch_threads(device), torch.set_grad_enabled(grad):
        pixels = tensors.pixels(len(object_ids) if per_object else 1)
        for _, chunk in _splat_chunks([x.shape[1]], len(x), device, pixels):
            xt = torch.tensor(x[None, chunk], requires_grad=grad, device=device)
            values = _silhouette_batch(xt, None, object_index, object_ids, tensors,
                                       np.arange(len(x))[chunk], splat_radius, per_object)[0]
            if values.requires_grad:  # no gradient asked, or no particle in view
                values.sum().backward()
                gradient[chunk] = xt.grad[0].cpu().numpy()
            per += values.detach().cpu().numpy()
    return per, gradient


def _splat_centres(x: torch.Tensor, world_to_optical: torch.Tensor,
                   K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pixel positions (..., N, 2), depths and in-front flags of world points ``x`` (..., N, 3).

    ``world_to_optical`` (..., 4, 4) and ``K`` (..., 3, 3): one camera, or several stacked (V
    cameras with ``x`` (..., 1, N, 3) give (..., V, N, ...)). A point behind the camera gets
    depth 1 (its position is then meaningless; ``front`` says so).
    """
    cam = x @ world_to_optical[..., :3, :3].transpose(-1, -2) + world_to_optical[..., None, :3, 3]
    front = cam[..., 2] > 1e-3
    z = torch.where(front, cam[..., 2], torch.ones_like(cam[..., 2]))
    focal = torch.stack([K[..., 0, 0], K[..., 1, 1]], dim=-1)[..., None, :]
    return cam[..., :2] / z[..., None] * focal + K[..., None, :2, 2], z, front


def _silhouette_batch(x: torch.Tensor, visible: torch.Tensor | None, object_index: np.ndarray,
                      object_ids: list[int], masks: MaskTensors, frames: np.ndarray,
                      splat_radius: float | np.ndarray, per_object: bool) -> torch.Tensor:
    """Per row and group (each object, or all with the scene-level loss) the loss of ``frames``.

    ``x`` (R, F, N, 3) the particles of R rows at ``frames`` (F,) of ``masks``, those
    ``visible`` (R, N) rendered (None: all); returns (R, G), differentiable in ``x``. Every
    view, frame and group is rendered by one launch (``_splats``): a group's splats reach what
    the largest of its splats in the view over ``frames`` needs (``_reach``), found on the
    device, so nothing is read back. A view's frames without its mask render nothing and count
    nothing.
    """
    rows, n_frames, n_particles = x.shape[:3]
    device = x.device
    n_groups = len(object_ids) if per_object else 1
    views = tuple(v for v in range(len(masks.views)) if masks.framed[v][frames].any())
    if not views or not n_particles:
        return x.new_zeros((rows, n_groups))
    index = _uploaded(object_index, device, torch.int64)
    radius = _uploaded(np.broadcast_to(np.asarray(splat_radius, dtype=np.float64), (len(object_ids),)),
                       device)[index]  # (N,) each particle's object's
    group = index if per_object else torch.zeros_like(index)
    shown = _uploaded(frames, device)
    world_to_optical, K, size, framed = masks.cameras(views)
    uv, z, front = _splat_centres(x[:, :, None], world_to_optical, K)  # (R, F, V, N, ...)
    sigma = torch.clamp(K[:, 0, 0, None] * radius / z, min=0.5)
    valid = front & framed[shown][None, :, :, None]
    if visible is not None:
        valid = valid & visible[:, None, None, :]
    # each (row, view, group)'s largest splat over the frames, as (R, F, V, G) images' reach
    largest = torch.where(valid, sigma.detach(), -math.inf).amax(dim=1)
    largest = largest.new_full((rows, len(views), n_groups), -math.inf).scatter_reduce(
        2, group.expand_as(largest), largest, "amax")
    images = rows * n_frames * len(views)
    canvas = _Canvas(group.to(torch.int32), n_groups,
                     _reach(largest)[:, None].expand(-1, n_frames, -1, -1).reshape(-1),
                     size[:, 0].repeat(rows * n_frames), size[:, 1].repeat(rows * n_frames), masks.stride(views))
    total = _SplatSum.apply(uv.reshape(images, n_particles, 2), sigma.reshape(images, n_particles),
                            valid.reshape(images, n_particles), canvas)
    soft = -torch.expm1(total).unflatten(0, (rows, n_frames, len(views), n_groups))
    groups = tuple((object_ids[k],) for k in range(len(object_ids))) if per_object else (tuple(object_ids),)
    target, known, pixels = masks.shown_in(views, groups, shown)  # (F, V, G, stride), (F, V, G)
    per_image = ((soft - target).abs() * known).sum(dim=-1) / pixels.clamp(min=1)
    # images where every pixel is another object's, or no particle of the group is in view: nothing
    members = torch.nn.functional.one_hot(group, n_groups).to(torch.float64)
    counted = (pixels > 0) & ((valid.to(torch.float64) @ members) > 0)
    return (per_image * counted * masks.frame_weight[shown][None, :, None, None]).sum(dim=(1, 2))


SPLAT_SHARES = (0.1, 1.0)
"""Range of the calibrated splat radius, in particle spacings (``calibrated_splat_radius``)."""


def calibrated_splat_radius(x: np.ndarray, object_id: int, views: list[View], masks: dict[str, np.ndarray],
                            spacing: float, device: str = "cpu", steps: int = 20) -> float | None:
    """The splat radius (m) at which one object's particles ``x`` (N, 3) cover as many pixels as ``masks`` show of it.

    Meant for the frame the particles were lifted from, where the twin's silhouettes should be
    the masks'. A recording's masks may draw an object wider or narrower than the particles
    lifted from them (the visual hull is wider than the object, and more so for a cube than a
    ball; a renderer may draw each particle as a ball wider than its spacing): at a fixed radius
    every frame's silhouette is then off the same way, and the fit answers through the
    material, with a less bulging object for silhouettes drawn too wide. The soft mask's pixel
    mass over the pixels known for the object (as the loss counts them), summed over the views,
    grows with the radius; bisection (``steps``) finds where it equals the masks' within
    ``SPLAT_SHARES`` particle spacings, clamped there. None where no view shows the object.
    """
    shown = [v for v in views if v.name in masks and np.any(masks[v.name] == object_id)]
    if not shown or not len(x):
        return None
    tensors = MaskTensors.of(shown, [masks], device)
    x = torch.as_tensor(np.asarray(x, dtype=np.float64), device=device)
    # what does not depend on the radius, per view: the particles in front, the pixels known
    placed = []
    for v, view in enumerate(shown):
        uv, z, front = _splat_centres(x, tensors.world_to_optical[v], tensors.K[v])
        target, known, _ = tensors.shown(v, (object_id,), slice(0, 1))
        placed.append((view, tensors.K[v][0, 0], uv[front], z[front], target[0], known[0]))

    def excess(radius: float) -> float:
        total = 0.0
        for view, focal, uv, z, target, known in placed:
            if not len(uv):  # none of the particles in front of the camera
                total -= float((target * known).sum())
                continue
            sigma = torch.clamp(focal * radius / z, min=0.5)
            every = torch.ones((1, len(uv)), dtype=torch.bool, device=device)
            soft = _soft_masks(uv[None], sigma[None], every, int(_reach(sigma.amax())), view.height, view.width)[0]
            total += float(((soft - target) * known).sum())
        return total

    lo, hi = (share * spacing for share in SPLAT_SHARES)
    with torch_threads(device), torch.no_grad():
        if excess(lo) >= 0.0:
            return lo
        if excess(hi) <= 0.0:
            return hi
        for _ in range(steps):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if excess(mid) < 0.0 else (lo, mid)
    return 0.5 * (lo + hi)


def silhouette_loss(x: np.ndarray, object_index: np.ndarray, object_ids: list[int],
                    views: list[View], masks: dict[str, np.ndarray], splat_radius: float | np.ndarray,
                    per_object: bool = True, device: str = "cpu") -> tuple[float, np.ndarray]:
    """``silhouette_losses`` of one frame: particles ``x`` (N, 3), masks by view name."""
    loss, grad = silhouette_losses(np.asarray(x)[None], object_index, object_ids, views, [masks],
                                   splat_radius, per_object, device)
    return loss, grad[0]
