"""Synthetic camera rigs: where the cameras stand, how they look, and the ray of every pixel.

What it is for: building ``T_world_optical`` poses (look-at, a ring or a hemisphere of cameras
around a point) and distortion-free pinhole intrinsics for the synthetic recorders, and the
per-pixel viewing rays that their renderers cast.
What it is not for: calibrating real cameras or projecting points (``CameraIntrinsics.project``
does that, and the tests use it as the independent check of what is rendered here).

Conventions (DESIGN.md): world z up; optical frames x right, y down, z forward; pixel centres at
integer coordinates; a ray ``d`` of a pixel has optical z = 1, so the ray parameter along it is
the depth along the optical axis.
"""

from __future__ import annotations

import math

import numpy as np

from mosiv_ros.io.recording import CameraIntrinsics

WORLD_UP = np.array([0.0, 0.0, 1.0])


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """T_world_optical of a camera at ``eye`` looking at ``target``, image x level with the world.

    A camera looking straight down or up (no horizon to level with) gets image x along world x.
    """
    eye, target = np.asarray(eye, dtype=np.float64), np.asarray(target, dtype=np.float64)
    z = target - eye
    norm = np.linalg.norm(z)
    if norm == 0:
        raise ValueError(f"camera at {eye.tolist()} cannot look at its own position")
    z /= norm
    x = np.cross(z, WORLD_UP)  # right: forward x world-up
    if np.linalg.norm(x) < 1e-9:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # down, so that x, y, z is right-handed
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def ring_poses(
    count: int, radius: float, height: float, target: np.ndarray, start_angle: float = 0.0
) -> list[np.ndarray]:
    """``count`` cameras evenly spaced on a horizontal circle, all looking at ``target``.

    The circle has ``radius`` (m) around the vertical through ``target`` and lies at world z =
    ``height``; camera i stands at azimuth ``start_angle + 2 pi i / count`` (radians, from +x).
    """
    target = np.asarray(target, dtype=np.float64)
    poses = []
    for i in range(count):
        angle = start_angle + 2.0 * math.pi * i / count
        eye = np.array([target[0] + radius * math.cos(angle), target[1] + radius * math.sin(angle),
                        height])
        poses.append(look_at(eye, target))
    return poses


def hemisphere_poses(
    count: int, radius: float, target: np.ndarray, min_elevation: float, max_elevation: float
) -> list[np.ndarray]:
    """``count`` cameras spread evenly over a spherical cap around ``target``, looking at it.

    Cameras stand at distance ``radius`` (m) from ``target``, at elevations (radians above the
    horizontal through ``target``) between ``min_elevation`` and ``max_elevation``, on a
    Fibonacci spiral (equal area per camera, successive azimuths a golden angle apart).
    """
    target = np.asarray(target, dtype=np.float64)
    z_lo, z_hi = math.sin(min_elevation), math.sin(max_elevation)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    poses = []
    for i in range(count):
        z = z_lo + (z_hi - z_lo) * (i + 0.5) / count  # uniform in z = uniform in area on a sphere
        r = math.sqrt(max(0.0, 1.0 - z * z))
        direction = np.array([r * math.cos(golden * i), r * math.sin(golden * i), z])
        poses.append(look_at(target + radius * direction, target))
    return poses


def pinhole(
    width: int,
    height: int,
    horizontal_fov: float | None = None,
    fx: float | None = None,
    fy: float | None = None,
    cx: float | None = None,
    cy: float | None = None,
) -> CameraIntrinsics:
    """Distortion-free pinhole intrinsics from ``fx`` (pixels) or ``horizontal_fov`` (radians).

    ``fy`` defaults to ``fx`` (square pixels), the principal point to the image centre
    ((width - 1) / 2, (height - 1) / 2).
    """
    if fx is None:
        if horizontal_fov is None or not 0 < horizontal_fov < math.pi:
            raise ValueError(f"need fx or a horizontal_fov in (0, pi), got {horizontal_fov}")
        fx = 0.5 * width / math.tan(0.5 * horizontal_fov)
    fy = fx if fy is None else fy
    cx = (width - 1) / 2 if cx is None else cx
    cy = (height - 1) / 2 if cy is None else cy
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return CameraIntrinsics(width=width, height=height, K=K, D=np.zeros(5))


def pixel_rays(intrinsics: CameraIntrinsics) -> np.ndarray:
    """Optical-frame ray directions (H * W, 3) through every pixel centre, row-major, z = 1."""
    if np.any(intrinsics.D):
        raise ValueError("pixel_rays: the synthetic renderers model distortion-free cameras only")
    u, v = np.meshgrid(np.arange(intrinsics.width, dtype=np.float64),
                       np.arange(intrinsics.height, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
    return pixels @ np.linalg.inv(intrinsics.K).T
