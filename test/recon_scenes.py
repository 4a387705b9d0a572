"""Analytic recordings with known geometry for the reconstruction and lifting tests.

Built from ``mosiv_ros.synth.shapes`` (ray-traced spheres seen by a ring of cameras): the sample
scene, and scenes of spheres placed where a test needs them (touching, hidden, leaving the view).
"""

from __future__ import annotations

import numpy as np

from mosiv_ros.io.recording import Camera, Frame, Recording
from mosiv_ros.io.scene import Scene, SceneObject
from mosiv_ros.synth.shapes import START_NS, Sphere, render, ring_camera_pose, ring_intrinsics

FPS = 10.0


def sphere_recording(spheres: list[Sphere], *, n_frames: int = 1, n_cameras: int = 4,
                     width: int = 160, height: int = 120) -> Recording:
    """``spheres`` on their closed-form paths, seen by ``n_cameras`` ring cameras at FPS."""
    intrinsics = ring_intrinsics(width, height)
    cameras = {}
    for index in range(n_cameras):
        T = ring_camera_pose(index, n_cameras)
        frames = [Frame(stamp(k), *render(intrinsics, T, spheres, k / FPS)) for k in range(n_frames)]
        cameras[f"cam{index}"] = Camera(f"cam{index}", intrinsics, T, frames)
    scene = Scene(objects=[SceneObject(s.id, s.name, s.family) for s in spheres])
    return Recording(cameras=cameras, scene=scene)


def stamp(k: int) -> int:
    """Stamp of frame k."""
    return START_NS + round(k * 1e9 / FPS)


def time_of(stamp_ns: int) -> float:
    """Seconds since frame 0 of a stamp."""
    return (stamp_ns - START_NS) * 1e-9


def ball_points(centre: np.ndarray, radius: float, spacing: float = 0.003) -> np.ndarray:
    """Ground-truth points filling a ball on a lattice of ``spacing``."""
    n = int(np.ceil(radius / spacing))
    axis = (np.arange(-n, n + 1)) * spacing
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    return centre + grid[np.linalg.norm(grid, axis=1) <= radius]


def touching_pair() -> list[Sphere]:
    """Two balls resting on the floor, touching at one point, and a third one apart."""
    return [
        Sphere(1, "left", "elastic", 0.10, (210, 40, 35), start=(-0.10, 0.0)),
        Sphere(2, "right", "plastic", 0.08, (40, 170, 60), start=(0.08, 0.0)),
        Sphere(3, "apart", "sand", 0.06, (45, 70, 200), start=(0.0, 0.35)),
    ]
