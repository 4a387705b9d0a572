"""What the identifier fits to: observed geometry per object per frame, and optional silhouettes.

``Observations`` holds, for frames at a fixed spacing ``frame_dt`` starting at the first observed
frame (the simulation's t = 0), each object's observed points (surface or occupancy, world frame)
and optionally calibrated views with their instance masks for the 2D loss, and surface tracks
attached to the particles (``TrackAttachment``) for the track loss. Objects are in the
simulator's order; ``object_ids`` gives each one's id in the masks.

What it is for: the data side of the losses (also as torch tensors on the device the losses are
computed on, ``Observations.tensors``), and the first-frame estimates the fit starts from
(initial velocities from centroid motion). What it is not for: building observations from
images (``mosiv_ros.recon``) or losses (``mosiv_ros.identify.losses``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy.spatial import cKDTree

MOTION_GAIN = 4.0
"""How much better (residual ratio) a moving fit must be than rest to be believed."""
NOISE_FLOOR = 0.001
"""Centroid noise (m) of a reconstruction that a motion must explain beyond."""
MOTION_FLOOR = 0.005
"""Least centroid displacement (m) from the second to the last of the frames used, for motion."""
ATTACH_NEIGHBOURS = 4
"""Particles a surface track is attached to (its nearest of its own object's)."""
ATTACH_REACH = 1.5
"""Farthest a track's nearest particle may be, in particle spacings: a track farther off its
object's particles is not on its surface (a wrong 3D point, another object's texture)."""


@dataclass
class TrackAttachment:
    """Surface tracks attached to the particles of the first frame, over frames 0..F-1.

    Track t follows the point ``sum_j weights[t, j] x[particles[t, j]] + offset[t]`` of the
    particles x (inverse-distance weights over its object's ``ATTACH_NEIGHBOURS`` nearest
    particles at frame 0, summing to 1; ``offset`` from that mean to the track at frame 0, so that
    the attached point starts on the track: the track is on the surface, the particles up to a
    spacing inside it). ``positions`` (F, T, 3) the tracked points, NaN where a track is not
    alive; ``confidence`` (F, T); ``object_index`` (T,) each track's object in the simulator's
    order.
    """

    particles: np.ndarray
    weights: np.ndarray
    offset: np.ndarray
    positions: np.ndarray
    confidence: np.ndarray
    object_index: np.ndarray

    @classmethod
    def attach(cls, positions: np.ndarray, confidence: np.ndarray, track_object_ids: np.ndarray,
               object_ids: list[int], x0: np.ndarray, particle_objects: np.ndarray, spacing: float
               ) -> tuple[TrackAttachment, int]:
        """Attach the tracks alive at frame 0 to the particles ``x0`` (N, 3) of their objects.

        ``positions`` (F, T, 3) and ``confidence`` (F, T) as stored; ``track_object_ids`` (T,)
        each track's object id, ``object_ids`` the objects' ids in the order that
        ``particle_objects`` (N,) indexes; ``spacing`` the particles' spacing (m). Returns the
        attachment and how many tracks alive at frame 0 were dropped (an object not among
        ``object_ids``, or farther than ``ATTACH_REACH`` spacings from its particles).
        """
        index = {int(object_id): k for k, object_id in enumerate(object_ids)}
        track_objects = np.array([index.get(int(i), -1) for i in track_object_ids], dtype=int)
        alive = np.flatnonzero(np.isfinite(positions[0, :, 0]))
        n = ATTACH_NEIGHBOURS
        kept, particles, weights = [], [], []
        for k in np.unique(track_objects[alive]):
            mine = np.flatnonzero(particle_objects == k)
            if k < 0 or not len(mine):
                continue
            tracks = alive[track_objects[alive] == k]
            # an object of fewer than n particles: the missing neighbours are at infinity (weight 0)
            distance, nearest = cKDTree(x0[mine]).query(positions[0, tracks].reshape(-1, 3), k=n)
            near = distance[:, 0] <= ATTACH_REACH * spacing
            inverse = 1.0 / np.maximum(distance[near], 1e-9 * spacing)
            kept.append(tracks[near])
            particles.append(mine[np.minimum(nearest[near], len(mine) - 1)])
            weights.append(inverse / inverse.sum(axis=1, keepdims=True))
        kept = np.concatenate(kept) if kept else np.zeros(0, int)
        particles = np.concatenate(particles) if particles else np.zeros((0, n), int)
        weights = np.concatenate(weights) if weights else np.zeros((0, n))
        attachment = cls(particles, weights, np.zeros((len(kept), 3)), positions[:, kept], confidence[:, kept],
                         track_objects[kept])
        attachment.offset = positions[0, kept] - attachment.points(x0)
        return attachment, len(alive) - len(kept)

    @property
    def n_tracks(self) -> int:
        return len(self.object_index)

    def points(self, x: np.ndarray, tracks: slice | np.ndarray = slice(None)) -> np.ndarray:
        """(T, 3) the attached points of particles ``x`` (N, 3) (of the ``tracks`` chosen)."""
        return np.einsum("tj,tjc->tc", self.weights[tracks], x[self.particles[tracks]]) + self.offset[tracks]

    def select(self, frames: slice) -> TrackAttachment:
        """The attachment over a range of frames (the attachment itself stays)."""
        return replace(self, positions=self.positions[frames], confidence=self.confidence[frames])


@dataclass
class View:
    """A calibrated camera: pinhole ``K`` (3x3), ``T_world_optical`` (4x4), image size."""

    name: str
    K: np.ndarray
    T_world_optical: np.ndarray
    width: int
    height: int

    def project(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2) and depth along the optical axis (N,) of world points."""
        T = np.linalg.inv(self.T_world_optical)
        cam = x @ T[:3, :3].T + T[:3, 3]
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (cam[:, :2] / z[:, None]) * np.diag(self.K)[:2] + self.K[:2, 2]
        return uv, z


def padded(sets: list[np.ndarray], device: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Point sets (M_i, 3) as one padded float64 tensor (S, max M_i, 3) on ``device``.

    Zeros past each set's end; returned with which entries are points (S, max M_i).
    """
    size = max([len(p) for p in sets] + [1])
    points = np.zeros((len(sets), size, 3))
    valid = np.zeros((len(sets), size), dtype=bool)
    for i, p in enumerate(sets):
        points[i, : len(p)], valid[i, : len(p)] = p, True
    return torch.as_tensor(points, device=device), torch.as_tensor(valid, device=device)


@dataclass
class MaskTensors:
    """Calibrated views and their instance masks over frames as tensors on ``device``.

    ``masks[v]`` (F, H, W) int64 the object ids of view v (zeros where a frame has no mask of
    it), ``framed[v]`` (F,) on the host, which frames have one; ``frame_weight`` (F,) one over
    the number of views with a mask in each frame (0 for none); ``world_to_optical[v]`` (4, 4)
    and ``K[v]`` (3, 3) float64. What the silhouette loss reads.
    """

    views: list[View]
    masks: list[torch.Tensor]
    framed: list[np.ndarray]
    frame_weight: torch.Tensor
    world_to_optical: list[torch.Tensor]
    K: list[torch.Tensor]
    _derived: dict = field(default_factory=dict, repr=False)

    def shown(self, view: int, ids: tuple[int, ...], frames: torch.Tensor | slice
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """What a silhouette of objects ``ids`` in ``view`` is compared with at ``frames``.

        (F, H, W) float64 1 where the mask shows one of ``ids``; (F, H, W) float64 1 where it
        is known for them (theirs or background: another object's pixel may hide them); (F,)
        the known pixels' count. Derived from every frame's mask once per view and ids.
        """
        target, known, pixels = self._split(view, ids)
        return target[frames].double(), known[frames].double(), pixels[frames]

    def _split(self, view: int, ids: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``shown`` of every frame, the pixels as booleans, derived once per view and ids."""
        key = (view, ids)
        if key not in self._derived:
            mask = self.masks[view]
            target = torch.isin(mask, torch.as_tensor(ids, device=mask.device))
            known = target | (mask == 0)
            self._derived[key] = (target, known, known.sum(dim=(1, 2), dtype=torch.float64))
        return self._derived[key]

    def shown_in(self, views: tuple[int, ...], groups: tuple[tuple[int, ...], ...], frames: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``shown`` of each of ``views`` and groups of object ids at ``frames``, stacked.

        (F, V, G, P) float64 target and known pixels, each image flattened (row-major) and
        padded to the largest of the views with pixels neither target nor known; (F, V, G) the
        known pixels' count. Derived once per views and groups.
        """
        key = ("views", views, groups)
        if key not in self._derived:
            device = self.frame_weight.device
            target = torch.zeros((len(self.frame_weight), len(views), len(groups), self.stride(views)),
                                 dtype=torch.bool, device=device)
            known = torch.zeros_like(target)
            pixels = torch.zeros(target.shape[:3], dtype=torch.float64, device=device)
            for a, v in enumerate(views):
                for g, ids in enumerate(groups):
                    mine, seen, count = self._split(v, ids)
                    target[:, a, g, :mine[0].numel()] = mine.flatten(1)
                    known[:, a, g, :seen[0].numel()] = seen.flatten(1)
                    pixels[:, a, g] = count
            self._derived[key] = (target, known, pixels)
        target, known, pixels = self._derived[key]
        return target[frames].double(), known[frames].double(), pixels[frames]

    def stride(self, views: tuple[int, ...]) -> int:
        """The pixels of the largest of ``views``'s images (each of ``shown_in``'s rows)."""
        return max(self.views[v].height * self.views[v].width for v in views)

    def pixels(self, groups: int) -> int:
        """The image pixels a frame's silhouettes render: every view's, once for each of ``groups``."""
        return groups * sum(view.height * view.width for view in self.views)

    def cameras(self, views: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """What the silhouettes need of ``views``'s cameras, stacked.

        World-to-optical transforms (V, 4, 4), intrinsics (V, 3, 3), image sizes (V, 2) int32
        (height, width), and which frames have each view's mask (F, V) bool.
        """
        key = ("cameras", views)
        if key not in self._derived:
            device = self.frame_weight.device
            self._derived[key] = (
                torch.stack([self.world_to_optical[v] for v in views]), torch.stack([self.K[v] for v in views]),
                torch.tensor([[self.views[v].height, self.views[v].width] for v in views], dtype=torch.int32,
                             device=device),
                torch.as_tensor(np.stack([self.framed[v] for v in views], axis=1), device=device))
        return self._derived[key]

    @classmethod
    def of(cls, views: list[View], masks: list[dict[str, np.ndarray]], device: str) -> MaskTensors:
        """``masks[f][view name]`` (H, W) as tensors on ``device``."""
        framed = [np.array([v.name in m for m in masks], dtype=bool) for v in views]
        stacks = []
        for v, has in zip(views, framed, strict=True):
            stack = np.zeros((len(masks), v.height, v.width), dtype=np.int64)
            for f in np.flatnonzero(has):
                stack[f] = masks[f][v.name]
            stacks.append(torch.as_tensor(stack, device=device))
        counts = np.sum(framed, axis=0, dtype=np.float64) if views else np.zeros(len(masks))
        weight = np.divide(1.0, counts, out=np.zeros(len(masks)), where=counts > 0)
        return cls(list(views), stacks, framed, torch.as_tensor(weight, device=device),
                   [torch.as_tensor(np.linalg.inv(v.T_world_optical), device=device) for v in views],
                   [torch.as_tensor(v.K, device=device) for v in views])


@dataclass
class TrackTensors:
    """A ``TrackAttachment`` as tensors on one device (positions zero where a track is not alive)."""

    particles: torch.Tensor
    weights: torch.Tensor
    offset: torch.Tensor
    positions: torch.Tensor
    alive: torch.Tensor
    confidence: torch.Tensor
    object_index: torch.Tensor

    @classmethod
    def of(cls, tracks: TrackAttachment, device: str) -> TrackTensors:
        alive = np.isfinite(tracks.positions[..., 0])
        return cls(*(torch.as_tensor(a, device=device) for a in (
            tracks.particles.astype(np.int64), tracks.weights, tracks.offset,
            np.where(alive[..., None], tracks.positions, 0.0), alive, tracks.confidence,
            tracks.object_index.astype(np.int64))))


@dataclass
class ObservedTensors:
    """``Observations`` as tensors on one device, for the losses computed there.

    ``points[k]`` (F, M, 3) and ``valid[k]`` (F, M): object k's observed points per frame,
    padded (``padded``); ``union``/``union_valid`` all objects' together (the scene-level
    loss); ``masks`` the views' masks (None without masks), ``tracks`` the tracks (None
    without). ``blocks[k]``: object k's points (-1: the union) sorted for the nearest
    neighbours (``losses.TargetBlocks``), every frame's, built on first use.
    """

    points: list[torch.Tensor]
    valid: list[torch.Tensor]
    union: torch.Tensor
    union_valid: torch.Tensor
    masks: MaskTensors | None
    tracks: TrackTensors | None
    blocks: dict = field(default_factory=dict)


@dataclass
class Observations:
    """Observed per-object geometry over frames 0..F-1 at ``frame_dt`` seconds apart.

    ``points[f][k]`` (M, 3) are object k's points at frame f (M may be 0 where it was not seen).
    ``masks[f][view name]`` (H, W) holds object ids (0 = background) for the views in ``views``.
    ``tracks`` covers the same frames.
    """

    frame_dt: float
    points: list[list[np.ndarray]]
    object_ids: list[int]
    views: list[View] = field(default_factory=list)
    masks: list[dict[str, np.ndarray]] = field(default_factory=list)
    start_ns: int = 0
    tracks: TrackAttachment | None = None
    """Surface tracks attached to the first frame's particles (None: no track loss)."""
    _trees: dict[int, list] = field(default_factory=dict, init=False, repr=False, compare=False)
    _tensors: dict[str, ObservedTensors] = field(default_factory=dict, init=False, repr=False,
                                                 compare=False)

    def trees(self, frame: int) -> list[cKDTree | None]:
        """KD-trees of each object's points at ``frame`` (built once, None where empty)."""
        if frame not in self._trees:
            self._trees[frame] = [cKDTree(p) if len(p) else None for p in self.points[frame]]
        return self._trees[frame]

    def tensors(self, device: str) -> ObservedTensors:
        """The observations as tensors on torch ``device`` (built once per device)."""
        if device not in self._tensors:
            objects = [padded([frame[k] for frame in self.points], device) for k in range(self.n_objects)]
            union = padded([np.concatenate([np.zeros((0, 3)), *frame]) for frame in self.points], device)
            self._tensors[device] = ObservedTensors(
                [p for p, _ in objects], [v for _, v in objects], *union,
                MaskTensors.of(self.views, self.masks, device) if self.masks else None,
                TrackTensors.of(self.tracks, device) if self.tracks is not None else None)
        return self._tensors[device]

    def __post_init__(self) -> None:
        if self.frame_dt <= 0:
            raise ValueError(f"frame_dt must be positive, got {self.frame_dt}")
        k = len(self.object_ids)
        for f, frame in enumerate(self.points):
            if len(frame) != k:
                raise ValueError(f"frame {f}: {len(frame)} point sets for {k} objects")
        if self.masks and len(self.masks) != len(self.points):
            raise ValueError(f"{len(self.masks)} mask frames for {len(self.points)} point frames")
        if self.tracks is not None and len(self.tracks.positions) != len(self.points):
            raise ValueError(f"{len(self.tracks.positions)} track frames for {len(self.points)} point frames")

    @property
    def n_frames(self) -> int:
        return len(self.points)

    @property
    def n_objects(self) -> int:
        return len(self.object_ids)

    def centroids(self) -> np.ndarray:
        """(F, K, 3) centroid of each object's points per frame, NaN where it has none."""
        out = np.full((self.n_frames, self.n_objects, 3), np.nan)
        for f, frame in enumerate(self.points):
            for k, pts in enumerate(frame):
                if len(pts):
                    out[f, k] = pts.mean(axis=0)
        return out

    def initial_velocities(self, frames: int = 4, horizon: int = 8) -> np.ndarray:
        """(K, 3) centroid velocity at t = 0 from each object's first ``frames`` observed frames.

        A frame without the object's points (lost by the stream, or the object hidden) is passed
        over, within the first ``horizon`` frames: a stream that lost frames 1-3 still gives its
        thrown ball a velocity, from frames 0, 4, 5 and 6 at their own times.

        Two motions are fitted to each object's centroids by least squares: at rest (x = x0)
        and uniformly accelerated (x = x0 + v0 t + a t^2 / 2, a free: gravity in flight,
        friction when sliding; a constant-velocity fit would return the mean velocity of a
        decelerating object). Rest is kept unless the motion fits more than ``MOTION_GAIN``
        times better (plus a millimetre of reconstruction noise per frame) and the centroid still
        moves ``MOTION_FLOOR`` after the first frame: a resting object's hull jitters as others
        move past it (or jumps once where it was occluded), and a difference of frames would
        read that as a velocity.
        """
        c = self.centroids()[:horizon]
        t = np.arange(len(c)) * self.frame_dt
        v0 = np.zeros((self.n_objects, 3))
        for k in range(self.n_objects):
            seen = np.flatnonzero(~np.isnan(c[:, k, 0]))[:frames]
            if len(seen) < 2:
                continue
            tk, ck = t[seen], c[seen, k]
            rest = float(np.sum((ck - ck.mean(axis=0)) ** 2))
            columns = [np.ones_like(tk), tk] + ([0.5 * tk**2] if len(tk) >= 3 else [])
            A = np.stack(columns, axis=1)
            coef = np.linalg.lstsq(A, ck, rcond=None)[0]
            moving = float(np.sum((A @ coef - ck) ** 2))
            # the motion must go on after the first frame, whose hull alone may be off (an
            # object occluded in it jumps once and stays)
            goes_on = len(tk) < 4 or np.linalg.norm(ck[-1] - ck[1]) > MOTION_FLOOR
            if goes_on and moving < rest / MOTION_GAIN - len(tk) * NOISE_FLOOR**2:
                v0[k] = coef[1]
        return v0

    def select(self, frames: slice) -> Observations:
        """The observations of a range of frames (the first one becomes frame 0)."""
        start = frames.start or 0
        return Observations(self.frame_dt, self.points[frames], self.object_ids, self.views,
                            self.masks[frames] if self.masks else [],
                            self.start_ns + int(round(start * self.frame_dt * 1e9)),
                            self.tracks.select(frames) if self.tracks is not None else None)
