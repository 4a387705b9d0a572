"""Rendering for the synthetic recorders: RGB, instance mask and depth from one z-buffer.

What it is for: turning a scene instant (simulation particles, a kinematic gripper, a floor)
into the three images of one camera, consistent with each other by construction: every pixel
takes the nearest surface along its ray, and that one surface gives its colour, its mask id and
its depth. No external renderer.
What it is not for: photorealism, lens distortion (cameras are ideal pinholes), or anything
physical: positions come from the simulator.

Model:

- Particles are drawn as the solid they fill (``ParticleSolid``), each label's on its own (two
  objects in contact touch, they do not merge): the region where their density
  rho(x) = sum_i (V_i / h^3) N((x - x_i) / h) reaches 1/2, with N the tensor-product quadratic
  B-spline of width ``spacing`` h and V_i each particle's volume. On an undeformed lattice rho
  is 1 inside and the level 1/2 lies half a spacing beyond the outer particles: a face of a
  sampled box is drawn where the box's face is, and the drawn solid has the particles' volume
  (a union of balls around the particles would look larger than the solid). rho is sampled on
  a grid of h / 3 and interpolated; each ray marches it in steps of h / 4 from where it enters
  the particles' box and refines the first crossing by bisection. A particle outside the level
  set (a lone one, a thin spray) is drawn as a ball of its own volume instead, so nothing with
  volume is invisible.
- The floor is the plane ``normal . x = height``, checkered in its own plane, a square of
  ``half_size`` around the point of the plane nearest to the origin.
- Shading is Lambert (ambient + one directional light) with the normal and albedo of the particle
  nearest the surface point; a particle's normal is the gradient of a Gaussian-weighted density
  of its own group.
- mask: the label of the particle nearest the surface point (object ids 1..K; 0 for the
  floor, a gripper and the background); depth: 32FC1 metres along the optical z axis to the nearest surface, the floor
  included; NaN where the ray hits nothing (the ROS "no return").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

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
GRID_DIVISIONS = 3  # density grid cells per particle spacing
MARCH_STEP = 0.25  # ray-marching step, in particle spacings
BISECTIONS = 6  # refinements of a crossing: to MARCH_STEP / 64 spacings
_CANDIDATES_PER_BATCH = 2_000_000  # (pixel, ball) pairs tested at once
_SAMPLES_PER_BATCH = 2_000_000  # ray samples evaluated at once


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
class ParticleSolid:
    """Particles to draw as the solid they fill (see the module docstring).

    Centres ``x`` (M, 3) world, ``label`` (M,) mask ids, ``albedo`` (M, 3) 0..255, unit
    ``normal`` (M, 3) world (for shading), ``spacing`` (m) the lattice spacing the particles were
    sampled at, ``volume`` (M,) m^3 each (None: spacing^3 each).
    """

    x: np.ndarray
    label: np.ndarray
    albedo: np.ndarray
    normal: np.ndarray
    spacing: float
    volume: np.ndarray | None = None

    @cached_property
    def weight(self) -> np.ndarray:
        """Each particle's volume in lattice cells, V_i / spacing^3 (M,)."""
        if self.volume is None:
            return np.ones(len(self.x))
        return np.asarray(self.volume, dtype=np.float64) / self.spacing**3

    @cached_property
    def parts(self) -> list[_Part]:
        """One solid per label: the particles with volume that carry it."""
        parts = []
        for label in np.unique(self.label):
            index = np.flatnonzero((self.label == label) & (self.weight > 0))
            if len(index):
                density = Density(self.x[index], self.weight[index], self.spacing)
                lone = index[density.rho(self.x[index]) < 0.5]
                parts.append(_Part(index, density, cKDTree(self.x[index]), lone))
        return parts


@dataclass
class _Part:
    """One label's particles ``index``, their ``density``, search ``tree`` and ``lone`` ones.

    ``lone``: those outside the level set, drawn as balls of their own volume.
    """

    index: np.ndarray
    density: Density
    tree: cKDTree
    lone: np.ndarray


def quadratic_bspline(r: np.ndarray) -> np.ndarray:
    """The quadratic B-spline N(r), support |r| < 1.5, summing to 1 over any unit lattice."""
    r = np.abs(r)
    return np.where(r < 0.5, 0.75 - r * r, np.where(r < 1.5, 0.5 * (1.5 - r) ** 2, 0.0))


class Density:
    """The particles' density rho (module docstring) on a grid of ``spacing / GRID_DIVISIONS``.

    ``rho(points)`` interpolates it trilinearly (0 outside the grid); ``lo`` and ``hi`` bound the
    region where it can be non-zero.
    """

    def __init__(self, x: np.ndarray, weight: np.ndarray, spacing: float) -> None:
        x = np.asarray(x, dtype=np.float64)
        self.step = spacing / GRID_DIVISIONS
        reach = 1.5 * spacing  # the kernel's support
        self.lo = x.min(axis=0) - reach
        self.hi = x.max(axis=0) + reach
        origin = self.lo - 2 * self.step
        self.origin = origin
        self.shape = np.ceil((self.hi - origin) / self.step).astype(np.int64) + 3
        nodes = np.arange(-math.ceil(1.5 * GRID_DIVISIONS), math.ceil(1.5 * GRID_DIVISIONS) + 2)
        values = np.zeros(int(np.prod(self.shape)))
        for chunk in np.array_split(np.arange(len(x)), 1 + len(x) // 20_000):
            base = np.floor((x[chunk] - origin) / self.step).astype(np.int64)
            index = base[:, :, None] + nodes  # (P, 3, K) node index per axis
            w = quadratic_bspline((origin[None, :, None] + index * self.step - x[chunk, :, None]) / spacing)
            flat = (index[:, 0, :, None, None] * self.shape[1] + index[:, 1, None, :, None]) * self.shape[2] \
                + index[:, 2, None, None, :]
            w3 = weight[chunk, None, None, None] * w[:, 0, :, None, None] * w[:, 1, None, :, None] \
                * w[:, 2, None, None, :]
            values += np.bincount(flat.ravel(), w3.ravel(), minlength=values.size)
        self.values = values.reshape(self.shape)

    def rho(self, points: np.ndarray) -> np.ndarray:
        f = (points - self.origin) / self.step
        i = np.floor(f).astype(np.int64)
        t = f - i
        inside = np.all((i >= 0) & (i < self.shape - 1), axis=-1)
        i = np.where(inside[..., None], i, 0)
        out = np.zeros(points.shape[:-1])
        for corner in np.ndindex(2, 2, 2):
            w = np.prod([t[..., a] if corner[a] else 1.0 - t[..., a] for a in range(3)], axis=0)
            out += w * self.values[i[..., 0] + corner[0], i[..., 1] + corner[1], i[..., 2] + corner[2]]
        return np.where(inside, out, 0.0)


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
    intrinsics: CameraIntrinsics, centres: np.ndarray, radius: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (H * W,): depth of the nearest ball along its ray (inf if none), that ball's index.

    ``centres`` (M, 3) are in the optical frame, ``radius`` (M,). Balls not wholly in front of
    the camera are skipped.
    """
    K = intrinsics.K
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    w, h = intrinsics.width, intrinsics.height
    depth = np.full(w * h, np.inf)
    owner = np.full(w * h, -1, dtype=np.int64)
    ahead = np.flatnonzero(centres[:, 2] > radius * (1.0 + 1e-6))
    c, r = centres[ahead], radius[ahead]
    u0 = np.rint(fx * c[:, 0] / c[:, 2] + cx).astype(np.int64)
    v0 = np.rint(fy * c[:, 1] / c[:, 2] + cy).astype(np.int64)
    # Footprint half-width: the ball's projected radius bound f r / (z - r), plus rounding.
    half = np.ceil(max(fx, fy) * r / (c[:, 2] - r) + 0.5).astype(np.int64)
    for size in np.unique(half):
        offsets = np.arange(-size, size + 1)
        du, dv = (a.ravel() for a in np.meshgrid(offsets, offsets))
        members = np.flatnonzero(half == size)
        for chunk in np.array_split(members, 1 + len(members) * du.size // _CANDIDATES_PER_BATCH):
            u = (u0[chunk, None] + du).ravel()
            v = (v0[chunk, None] + dv).ravel()
            ball = np.repeat(chunk, du.size)
            keep = (u >= 0) & (u < w) & (v >= 0) & (v < h)
            u, v, ball = u[keep], v[keep], ball[keep]
            d = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones(len(u))], axis=1)
            centre = c[ball]
            # |s d - centre|^2 = r^2: a s^2 - 2 b s + k = 0, nearest root (b - sqrt(b^2 - a k)) / a
            a = np.einsum("ij,ij->i", d, d)
            b = np.einsum("ij,ij->i", d, centre)
            k = np.einsum("ij,ij->i", centre, centre) - r[ball] ** 2
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


def _level_set_depth(density: Density, origin: np.ndarray, rays: np.ndarray, spacing: float) -> np.ndarray:
    """Per ray (M,): ray parameter of the first point where rho reaches 1/2 (inf if none).

    ``rays`` (M, 3) are world directions from ``origin``.
    """
    depth = np.full(len(rays), np.inf)
    d = np.where(np.abs(rays) < 1e-12, 1e-12, rays)
    a, b = (density.lo - origin) / d, (density.hi - origin) / d
    near = np.maximum(np.minimum(a, b).max(axis=1), 0.0)
    far = np.maximum(a, b).min(axis=1)
    candidates = np.flatnonzero(far > near)
    if len(candidates) == 0:
        return depth
    step = MARCH_STEP * spacing / np.linalg.norm(rays[candidates], axis=1)
    count = np.ceil((far[candidates] - near[candidates]) / step).astype(np.int64) + 1
    for chunk in np.array_split(np.arange(len(candidates)),
                                1 + len(candidates) * int(count.max()) // _SAMPLES_PER_BATCH):
        ray = candidates[chunk]
        k = np.arange(int(count[chunk].max()))
        s = near[ray, None] + step[chunk, None] * k
        solid = density.rho(origin + s[:, :, None] * rays[ray, None, :]) >= 0.5
        solid &= k < count[chunk, None]
        hit = solid.any(axis=1)
        first = solid.argmax(axis=1)[hit]
        ray, hi = ray[hit], s[hit, first]
        lo = np.maximum(hi - step[chunk][hit], near[ray])
        for _ in range(BISECTIONS):
            mid = 0.5 * (lo + hi)
            inside = density.rho(origin + mid[:, None] * rays[ray]) >= 0.5
            hi, lo = np.where(inside, mid, hi), np.where(inside, lo, mid)
        depth[ray] = hi
    return depth


def render_view(
    intrinsics: CameraIntrinsics, T_world_optical: np.ndarray, solid: ParticleSolid, floor: Floor | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb uint8 (H, W, 3), mask (H, W) uint8 or uint16, depth float32 (H, W)) of one camera."""
    R, t = T_world_optical[:3, :3], T_world_optical[:3, 3]
    rays = pixel_rays(intrinsics) @ R.T  # world directions, optical z = 1: the parameter is depth
    depth = np.full(len(rays), np.inf)
    owner = np.full(len(rays), -1, dtype=np.int64)
    for part in solid.parts:
        part_depth = _level_set_depth(part.density, t, rays, solid.spacing)
        nearer = part_depth < depth
        depth[nearer] = part_depth[nearer]
        owner[nearer] = part.index[part.tree.query(t + depth[nearer, None] * rays[nearer])[1]]
    lone = np.concatenate([part.lone for part in solid.parts] + [np.zeros(0, dtype=np.int64)])
    if len(lone):
        radius = np.cbrt(3.0 * solid.weight[lone] / (4.0 * math.pi)) * solid.spacing
        ball_depth, ball = _nearest_balls(intrinsics, (solid.x[lone] - t) @ R, radius)
        nearer = ball_depth < depth
        depth[nearer], owner[nearer] = ball_depth[nearer], lone[ball[nearer]]
    albedo = np.zeros((depth.size, 3))
    normal = np.zeros((depth.size, 3))
    on_object = owner >= 0
    albedo[on_object] = solid.albedo[owner[on_object]]
    normal[on_object] = solid.normal[owner[on_object]]
    if floor is not None:
        s, floor_albedo, floor_normal = floor.hit(t, rays)
        on_floor = s < depth
        depth[on_floor] = s[on_floor]
        on_object &= ~on_floor
        albedo[on_floor] = floor_albedo[on_floor]
        normal[on_floor] = floor_normal
    seen = np.isfinite(depth)
    rgb = np.where(seen[:, None], shade(albedo, normal), BACKGROUND_RGB)
    dtype = np.uint8 if solid.label.size == 0 or solid.label.max() <= 255 else np.uint16
    mask = np.zeros(depth.size, dtype=dtype)
    mask[on_object] = solid.label[owner[on_object]]
    h, w = intrinsics.height, intrinsics.width
    return (
        rgb.round().astype(np.uint8).reshape(h, w, 3),
        mask.reshape(h, w),
        np.where(seen, depth, np.nan).astype(np.float32).reshape(h, w),
    )
