"""A tiny analytic recording: coloured spheres on a floor, seen by a ring of cameras.

What it is for: a small sample bag (and in-memory Recording) with exactly known geometry, for
tests, demos and the bundled ``bags/shapes_demo``. Every pixel is ray-traced analytically
(ray-sphere and ray-plane intersection, numpy-vectorised). What it is not for: physics (the
physics-based recorder is ``synth.recorder``). The spheres follow closed-form paths (an elastic
ball bouncing in ballistic flight without losing speed, a ball sliding on the floor at a constant
velocity, a ball at rest); no material parameter shapes them, so a twin fits them only
approximately, and no ground-truth sidecar is written. The scene declares the floor it draws
(height 0, normal +z, friction undeclared), as a recording of a real floor would.

Conventions: world frame z up, floor the square |x|, |y| <= FLOOR_HALF_SIZE at z = 0; cameras on
a ring around the scene centre, optical frames x right, y down, z forward; pixel centres at
integer coordinates. Outputs per pixel:

- rgb: Lambert shading (ambient + directional light) of the nearest surface: sphere colour,
  grey checkered floor, or a dark background where the ray hits nothing;
- mask: id of the nearest sphere (so nearer spheres occlude farther ones), 0 elsewhere (floor and
  background alike);
- depth: 32FC1 metres along the optical z axis to the nearest surface, floor included, as a depth
  sensor would see it; NaN (the ROS convention for "no return") where the ray hits nothing.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mosiv_ros.io.bag import write_recording
from mosiv_ros.io.recording import Camera, CameraIntrinsics, Frame, Recording
from mosiv_ros.io.scene import DeclaredGround, Scene, SceneObject
from mosiv_ros.synth.cameras import look_at, pinhole, pixel_rays
from mosiv_ros.synth.render import BACKGROUND_RGB, Floor, shade

_LOG = logging.getLogger(__name__)

GRAVITY = 9.81  # m/s^2, along -z
FLOOR_HALF_SIZE = 1.2  # m
RING_RADIUS = 1.3  # m, horizontal distance of the cameras from the scene centre
CAMERA_HEIGHT = 1.0  # m
LOOK_AT = np.array([0.0, 0.0, 0.1])  # m
HORIZONTAL_FOV = math.radians(60.0)
START_NS = 1_700_000_000_000_000_000  # stamp of frame 0 (an ordinary epoch time)


@dataclass(frozen=True)
class Sphere:
    """A sphere on a closed-form path.

    The centre moves horizontally at ``velocity`` (m/s) from ``start`` (x, y) at t = 0. With
    ``bounce_speed`` > 0 it bounces elastically on the floor, leaving it upwards at that speed
    (ballistic flight in between), ``phase`` seconds into its first bounce at t = 0; with 0 it
    stays on the floor (rolling or at rest).
    """

    id: int
    name: str
    family: str
    radius: float
    rgb: tuple[int, int, int]
    start: tuple[float, float]
    velocity: tuple[float, float] = (0.0, 0.0)
    bounce_speed: float = 0.0
    phase: float = 0.0

    def centre(self, t: float) -> np.ndarray:
        """World position (m) of the centre at time ``t`` (s)."""
        x, y = np.add(self.start, np.multiply(self.velocity, t))
        height = 0.0
        if self.bounce_speed > 0:
            tau = (t + self.phase) % (2.0 * self.bounce_speed / GRAVITY)
            height = self.bounce_speed * tau - 0.5 * GRAVITY * tau * tau
        return np.array([x, y, self.radius + height])


def shapes_spheres(seed: int = 0) -> list[Sphere]:
    """The three spheres of the sample scene; ``seed`` jitters their starts and bounce phase.

    Their paths stay apart (no two spheres touch) for at least 2 s.
    """
    rng = np.random.default_rng(seed)
    jitter = rng.uniform(-0.03, 0.03, size=(3, 2))
    return [
        Sphere(
            1,
            "red_ball",
            "elastic",
            0.10,
            (210, 40, 35),
            start=(-0.05 + jitter[0, 0], 0.50 + jitter[0, 1]),
            velocity=(0.0, -0.3),
            bounce_speed=2.2,
            phase=float(rng.uniform(0.0, 0.4)),
        ),
        Sphere(
            2,
            "green_ball",
            "plastic",
            0.12,
            (40, 170, 60),
            start=(0.45 + jitter[1, 0], -0.35 + jitter[1, 1]),
            velocity=(-0.4, 0.0),
        ),
        Sphere(
            3,
            "blue_ball",
            "sand",
            0.08,
            (45, 70, 200),
            start=(0.35 + jitter[2, 0], 0.20 + jitter[2, 1]),
        ),
    ]


def ring_camera_pose(index: int, n_cameras: int) -> np.ndarray:
    """T_world_optical of camera ``index`` of ``n_cameras`` on the ring, looking at LOOK_AT."""
    angle = 2.0 * math.pi * index / n_cameras + 0.3
    eye = np.array([RING_RADIUS * math.cos(angle), RING_RADIUS * math.sin(angle), CAMERA_HEIGHT])
    return look_at(eye, LOOK_AT)


def ring_intrinsics(width: int, height: int) -> CameraIntrinsics:
    """Distortion-free pinhole with HORIZONTAL_FOV, square pixels, centred principal point."""
    return pinhole(width, height, HORIZONTAL_FOV)


def render(
    intrinsics: CameraIntrinsics,
    T_world_optical: np.ndarray,
    spheres: list[Sphere],
    t: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb, mask, depth) of the scene at time ``t`` seen by one camera (see module docstring)."""
    h, w = intrinsics.height, intrinsics.width
    # Rays o + s d with d's optical z = 1, so the ray parameter s is the depth along optical z.
    d = pixel_rays(intrinsics) @ T_world_optical[:3, :3].T
    o = T_world_optical[:3, 3]

    depth = np.full(h * w, np.inf)
    mask = np.zeros(h * w, dtype=np.uint8)
    albedo = np.zeros((h * w, 3))
    normal = np.zeros((h * w, 3))
    a = np.einsum("ij,ij->i", d, d)
    for sphere in spheres:
        c = sphere.centre(t)
        # |o + s d - c|^2 = r^2  ->  a s^2 + 2 b s + k = 0; nearest root (-b - sqrt(b^2 - a k)) / a
        b = d @ (o - c)
        k = (o - c) @ (o - c) - sphere.radius**2
        disc = b * b - a * k
        with np.errstate(invalid="ignore"):
            s = (-b - np.sqrt(disc)) / a
        nearer = (disc >= 0) & (s > 0) & (s < depth)
        depth[nearer] = s[nearer]
        mask[nearer] = sphere.id
        albedo[nearer] = sphere.rgb
        normal[nearer] = (o + s[nearer, None] * d[nearer] - c) / sphere.radius

    s, floor_albedo, floor_normal = Floor(half_size=FLOOR_HALF_SIZE).hit(o, d)
    on_floor = s < depth
    depth[on_floor] = s[on_floor]
    albedo[on_floor] = floor_albedo[on_floor]
    normal[on_floor] = floor_normal

    seen = np.isfinite(depth)
    rgb = np.where(seen[:, None], shade(albedo, normal), BACKGROUND_RGB)
    depth = np.where(seen, depth, np.nan).astype(np.float32)
    return rgb.round().astype(np.uint8).reshape(h, w, 3), mask.reshape(h, w), depth.reshape(h, w)


def make_shapes_recording(
    *,
    n_frames: int = 20,
    fps: float = 10.0,
    n_cameras: int = 3,
    width: int = 80,
    height: int = 60,
    seed: int = 0,
) -> Recording:
    """The sample recording: ``n_cameras`` ring cameras ``cam0..``, synchronised frames at ``fps``.

    Frame k has stamp START_NS + k / fps (s) and shows the spheres of ``shapes_spheres(seed)`` at
    t = k / fps. The scene declares the three spheres and the floor; there is no gripper.
    """
    if n_frames < 1 or n_cameras < 1 or fps <= 0:
        raise ValueError(
            f"need n_frames >= 1, n_cameras >= 1, fps > 0; got {n_frames}, {n_cameras}, {fps}"
        )
    spheres = shapes_spheres(seed)
    intrinsics = ring_intrinsics(width, height)
    offsets_ns = [round(k * 1e9 / fps) for k in range(n_frames)]
    cameras = {}
    for index in range(n_cameras):
        T = ring_camera_pose(index, n_cameras)
        frames = [
            Frame(START_NS + dt, *render(intrinsics, T, spheres, dt * 1e-9)) for dt in offsets_ns
        ]
        cameras[f"cam{index}"] = Camera(f"cam{index}", intrinsics, T, frames)
    scene = Scene(objects=[SceneObject(s.id, s.name, s.family) for s in spheres],
                  ground=DeclaredGround(height=0.0, normal=(0.0, 0.0, 1.0)))
    return Recording(cameras=cameras, scene=scene)


def write_shapes_bag(path: str | Path, *, storage: str = "mcap", **kw: Any) -> Path:
    """Write ``make_shapes_recording(**kw)`` as a bag at ``path`` (MCAP chunks zstd-compressed)."""
    recording = make_shapes_recording(**kw)
    path = write_recording(recording, path, storage=storage, compress=storage == "mcap")
    _LOG.info("wrote shapes sample bag %s", path)
    return path
