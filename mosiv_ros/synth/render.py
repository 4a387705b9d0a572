"""Rendering for the synthetic recorders: RGB, instance mask and depth from one z-buffer.

What it is for: turning a scene instant (simulation particles, a kinematic gripper, a floor)
into the three images of one camera, consistent with each other by construction: every pixel
takes the nearest surface along its ray, and that one surface gives its colour, its mask id and
its depth. No external renderer.
What it is not for: photorealism, lens distortion (cameras are ideal pinholes), or anything
physical: positions come from the simulator.

Model:

- Particles are drawn as balls of one radius around their centres (``Splats``), ray-traced
  exactly: each ball is intersected with the rays of the pixels in its screen footprint, and a
  z-buffer keeps the nearest hit. The visible surface of an object is thus the union of its
  particles' balls (it lies about ``radius - spacing / 2`` outside the solid the particles fill).
- The floor is the plane ``normal . x = height``, checkered in its own plane, a square of
  ``half_size`` around the point of the plane nearest to the origin.
- Shading is Lambert (ambient + one directional light) with per-particle normals: the gradient
  of a Gaussian-weighted density of each particle's own group, so surfaces look smooth instead of
  bumpy.
- mask: the label of the nearest ball (object ids 1..K; 0 for the floor, a gripper and the
  background); depth: 32FC1 metres along the optical z axis to the nearest surface, the floor
  included; NaN where the ray hits nothing (the ROS "no return").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mosiv_ros.io.recording import CameraIntrinsics
from mosiv_ros.synth.cameras import pixel_rays

CHECKER_SIZE = 0.2  # m, side of a floor square
FLOOR_RGB = (np.array([150.0, 150.0, 140.0]), np.array([105.0, 105.0, 100.0]))
BACKGROUND_RGB = np.array([30, 34, 44], dtype=np.uint8)
LIGHT_DIRECTION = np.array([0.4, 0.3, 1.0]) / np.linalg.norm([0.4, 0.3, 1.0])  # towards light
AMBIENT = 0.3
NEIGHBOURS = 16  # particles in a normal estimate
SPLAT_RADIUS = 0.8
"""Radius of a rendered particle ball, in particle spacings (> 1/sqrt(2): no see-through gaps);
the recorder and the twin's re-rendering draw particles alike."""
_CANDIDATES_PER_BATCH = 2_000_000  # (pixel, ball) pairs tested at once


@dataclass
class Floor:
    """A finite, checkered floor on the plane ``normal . x = height`` (normal normalised here)."""

    height: float = 0.0
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    half_size: float = 1.2

    def hit(self, origin: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ray parameter (inf where missed), albedo (M, 3) and unit normal (3,) of the floor.

        ``rays`` (M, 3) are world directions from ``origin``; the floor is seen from either side.
        """
        n = np.asarray(self.normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        e1 = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = e1 - (e1 @ n) * n
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (self.height - origin @ n) / (rays @ n)
        local = origin - self.height * n + np.nan_to_num(s, posinf=0.0, neginf=0.0)[:, None] * rays
        a, b = local @ e1, local @ e2
        inside = (s > 0) & (np.abs(a) <= self.half_size) & (np.abs(b) <= self.half_size)
        checker = (np.floor(a / CHECKER_SIZE) + np.floor(b / CHECKER_SIZE)) % 2 == 0
        albedo = np.where(checker[:, None], *FLOOR_RGB)
        return np.where(inside, s, np.inf), albedo, n


@dataclass
class Splats:
    """Balls of one ``radius`` (m) to draw.

    Centres ``x`` (M, 3) world, ``label`` (M,) mask ids, ``albedo`` (M, 3) 0..255, unit
    ``normal`` (M, 3) world, used for shading.
    """

    x: np.ndarray
    label: np.ndarray
    albedo: np.ndarray
    normal: np.ndarray
    radius: float


def surface_normals(x: np.ndarray, groups: np.ndarray, spacing: float) -> np.ndarray:
    """Outward unit normals (N, 3) of particles ``x`` (N, 3), from each particle's own group.

    The normal is the direction of steepest descent of a Gaussian density (width 1.5 spacing) of
    the group's particles; where that vanishes (deep inside, or a lone particle) it falls back to
    the direction away from the group's centroid.
    """
    normals = np.zeros_like(x, dtype=np.float64)
    h = 1.5 * spacing
    for group in np.unique(groups):
        index = np.flatnonzero(groups == group)
        points = x[index].astype(np.float64)
        k = min(NEIGHBOURS, len(points))
        distance, neighbour = cKDTree(points).query(points, k=k)
        distance, neighbour = distance.reshape(len(points), k), neighbour.reshape(len(points), k)
        weight = np.exp(-((distance / h) ** 2))
        gradient = np.einsum("ij,ijk->ik", weight, points[:, None, :] - points[neighbour])
        fallback = points - points.mean(axis=0)
        weak = np.linalg.norm(gradient, axis=1) < 1e-3 * spacing
        gradient[weak] = fallback[weak] + (np.linalg.norm(fallback[weak], axis=1, keepdims=True) == 0)
        normals[index] = gradient / np.linalg.norm(gradient, axis=1, keepdims=True)
    return normals


def shade(albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Lambert shading of ``albedo`` (M, 3) under the light, for unit world ``normal`` (M, 3)."""
    light = AMBIENT + (1.0 - AMBIENT) * np.clip(normal @ LIGHT_DIRECTION, 0.0, None)
    return np.clip(albedo * light[:, None], 0.0, 255.0)


def _nearest_balls(
    intrinsics: CameraIntrinsics, centres: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (H * W,): depth of the nearest ball along its ray (inf if none), that ball's index.

    ``centres`` are in the optical frame. Balls not wholly in front of the camera are skipped.
    """
    K = intrinsics.K
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    w, h = intrinsics.width, intrinsics.height
    depth = np.full(w * h, np.inf)
    owner = np.full(w * h, -1, dtype=np.int64)
    ahead = np.flatnonzero(centres[:, 2] > radius * (1.0 + 1e-6))
    c = centres[ahead]
    u0 = np.rint(fx * c[:, 0] / c[:, 2] + cx).astype(np.int64)
    v0 = np.rint(fy * c[:, 1] / c[:, 2] + cy).astype(np.int64)
    # Footprint half-width: the ball's projected radius bound f r / (z - r), plus rounding; then
    # the footprint's part inside the image, grouped by its size. A ball that grazes the lens
    # (z just above r) covers the whole image: unclipped, its square ran to millions of pixels
    # a side (a full-suite scene whose ball flew past a camera ran out of memory rendering).
    half = np.ceil(max(fx, fy) * radius / (c[:, 2] - radius) + 0.5).astype(np.int64)
    u_lo, u_hi = np.clip(u0 - half, 0, w), np.clip(u0 + half + 1, 0, w)
    v_lo, v_hi = np.clip(v0 - half, 0, h), np.clip(v0 + half + 1, 0, h)
    box = np.stack([u_hi - u_lo, v_hi - v_lo], axis=1)
    seen = np.flatnonzero((box > 0).all(axis=1))
    sizes, kind = np.unique(box[seen], axis=0, return_inverse=True)
    kind = kind.ravel()
    counts = np.bincount(kind, minlength=len(sizes))
    groups = np.split(seen[np.argsort(kind, kind="stable")], np.cumsum(counts))[:-1]
    for (width, height), members in zip(sizes, groups, strict=True):
        du, dv = (a.ravel() for a in np.meshgrid(np.arange(width), np.arange(height)))
        for chunk in np.array_split(members, 1 + len(members) * du.size // _CANDIDATES_PER_BATCH):
            u = (u_lo[chunk, None] + du).ravel()
            v = (v_lo[chunk, None] + dv).ravel()
            ball = np.repeat(chunk, du.size)
            d = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones(len(u))], axis=1)
            centre = c[ball]
            # |s d - centre|^2 = r^2: a s^2 - 2 b s + k = 0, nearest root (b - sqrt(b^2 - a k)) / a
            a = np.einsum("ij,ij->i", d, d)
            b = np.einsum("ij,ij->i", d, centre)
            k = np.einsum("ij,ij->i", centre, centre) - radius * radius
            disc = b * b - a * k
            hit = (disc >= 0) & (b > 0)
            if not hit.any():
                continue
            s = (b[hit] - np.sqrt(disc[hit])) / a[hit]
            pixel = (v * w + u)[hit]
            order = np.lexsort((s, pixel))
            first = order[np.r_[True, pixel[order][1:] != pixel[order][:-1]]]
            nearer = s[first] < depth[pixel[first]]
            depth[pixel[first][nearer]] = s[first][nearer]
            owner[pixel[first][nearer]] = ahead[ball[hit][first][nearer]]
    return depth, owner


def render_view(
    intrinsics: CameraIntrinsics, T_world_optical: np.ndarray, splats: Splats, floor: Floor | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb uint8 (H, W, 3), mask (H, W) uint8 or uint16, depth float32 (H, W)) of one camera."""
    R, t = T_world_optical[:3, :3], T_world_optical[:3, 3]
    rays = pixel_rays(intrinsics)
    depth, owner = _nearest_balls(intrinsics, (splats.x - t) @ R, splats.radius)
    albedo = np.zeros((depth.size, 3))
    normal = np.zeros((depth.size, 3))
    on_ball = owner >= 0
    albedo[on_ball] = splats.albedo[owner[on_ball]]
    normal[on_ball] = splats.normal[owner[on_ball]]
    if floor is not None:
        s, floor_albedo, floor_normal = floor.hit(t, rays @ R.T)
        on_floor = s < depth
        depth[on_floor] = s[on_floor]
        on_ball &= ~on_floor
        albedo[on_floor] = floor_albedo[on_floor]
        normal[on_floor] = floor_normal
    seen = np.isfinite(depth)
    rgb = np.where(seen[:, None], shade(albedo, normal), BACKGROUND_RGB)
    dtype = np.uint8 if splats.label.size == 0 or splats.label.max() <= 255 else np.uint16
    mask = np.zeros(depth.size, dtype=dtype)
    mask[on_ball] = splats.label[owner[on_ball]]
    h, w = intrinsics.height, intrinsics.width
    return (
        rgb.round().astype(np.uint8).reshape(h, w, 3),
        mask.reshape(h, w),
        np.where(seen, depth, np.nan).astype(np.float32).reshape(h, w),
    )
