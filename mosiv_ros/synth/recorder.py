"""The synthetic multi-camera recorder: scene file -> simulation -> images -> rosbag2 + truth.

What it is for: ``record`` simulates a laid-out scene with ``mosiv_ros.sim``, renders every
camera at every frame (RGB, instance mask, depth; ``render``), adds the scene's noise and
recorder effects, and writes a bag in the DESIGN.md layout with ``io.bag.write_recording``
(scene declaration in its metadata, gripper poses on ``/gripper/pose``), then the ground-truth
sidecars inside the bag directory (``ground_truth``).
What it is not for: parsing scene files (``scene_file``, ``layout``), benchmark suites
(``suite``), or the command line (``mosiv record`` in ``mosiv_ros.cli`` wraps ``record``).

Frames k = 0..n (n = duration * fps) are stamped ``start_stamp_ns + k / fps``; a camera with a
time offset shows the scene at k / fps + offset (particle positions interpolated linearly
between simulated frames, held before t = 0) under the same stamp. Noise and mask noise draw
from one generator seeded by ``seed``, so a recording is reproducible.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from mosiv_ros.io.bag import write_recording
from mosiv_ros.io.files import check_new_path
from mosiv_ros.io.recording import Camera, Frame, Recording
from mosiv_ros.io.scene import Scene, SceneObject
from mosiv_ros.progress import Progress
from mosiv_ros.sim import (
    BUILTIN_EFFECTS,
    MATERIAL_PARAMS,
    WALL_RETRIES,
    ObjectModel,
    Particles,
    SimConfig,
    Simulator,
    domain_around,
    reaches_walls,
)
from mosiv_ros.sim.boundaries import GROUND_PARAMS
from mosiv_ros.synth.bodies import gripper_points
from mosiv_ros.synth.effects import add_mask_noise, camera_offsets, declaration, simulator_effects
from mosiv_ros.synth.ground_truth import GroundTruthParticles, write_ground_truth
from mosiv_ros.synth.layout import Layout, lay_out
from mosiv_ros.synth.render import SPLAT_RADIUS, Floor, Splats, render_view, surface_normals
from mosiv_ros.synth.scene_file import CameraSpec, SceneSpec, check_recording_size

_LOG = logging.getLogger(__name__)


def record(spec: SceneSpec, out: str | Path, *, seed: int = 0, compress: bool = True,
           progress: Progress | None = None) -> Path:
    """Record ``spec`` as a new bag directory ``out`` (must not exist) with its sidecars.

    Raises OutputError when ``out`` exists or cannot be created (checked first), SceneError for a
    bad scene, ``mosiv_ros.sim`` errors when the simulation cannot run or diverges, BagError when
    the bag cannot be written.
    """
    check_new_path(out)  # before minutes of simulation, not after
    layout = lay_out(spec)
    check_recording_size(spec, len(layout.x))  # before the simulation holds the particles' paths
    offsets = camera_offsets(spec.effects)
    extra = math.ceil(max([0.0, *offsets.values()]) * spec.cameras.fps)  # frames a late camera needs
    positions, settings = simulate(layout, spec.n_frames + extra, progress)
    if spec.cameras.fit_motion:
        ball = SPLAT_RADIUS * spec.simulation.particle_spacing
        spec = replace(spec, cameras=fit_views(spec.cameras, positions, ball))
        layout = replace(layout, spec=spec)
    rng = np.random.default_rng(seed)
    cameras = render_cameras(layout, positions, offsets, rng, progress)
    ground, effects = declaration(spec.effects, spec.ground.height)
    scene = Scene(
        objects=[SceneObject(o.id, o.name, o.family if o.declared_family else None,
                             {p: o.params[p] for p in o.declared_params}) for o in spec.objects],
        gripper=spec.gripper.declaration() if spec.gripper else None,
        ground=ground,
        effects=effects,
    )
    frames = range(spec.n_frames + 1)
    gripper_poses = []
    if layout.collider is not None:
        gripper_poses = [(spec.stamp_ns(k), _pose_matrix(*layout.collider.pose(k / spec.cameras.fps)))
                         for k in frames]
    path = write_recording(Recording(cameras, scene, gripper_poses), out, compress=compress)
    particles = GroundTruthParticles(
        positions=positions[: spec.n_frames + 1],
        object_id=np.array([spec.objects[k].id for k in layout.object_index]),
        volume=layout.volume,
        stamps_ns=np.array([spec.stamp_ns(k) for k in frames]),
        times=np.array([k / spec.cameras.fps for k in frames]),
    )
    write_ground_truth(path, ground_truth_document(layout, settings, seed), particles)
    _LOG.info("recorded %s into %s: %d cameras x %d frames", spec.name, path, len(cameras), len(frames))
    return path


FIT_MARGIN_PX = 2.0
"""Pixels a fitted view keeps free between every particle ball and the image border."""
FIT_MAX_SCALE = 4.0
"""Farthest a fitted view moves its cameras: this many times their distance to the target."""


def fit_views(cameras: CameraSpec, positions: np.ndarray, radius: float) -> CameraSpec:
    """``cameras`` moved back from their target until every object stays inside every image.

    Every camera moves along its line of sight (orientation kept), all by the smallest common
    factor of their distances to the target (to 1 %; at most FIT_MAX_SCALE, with a warning where
    even that does not suffice) at which every particle's ball of ``radius`` at every frame of
    ``positions`` (frames, N, 3) projects inside the image with FIT_MARGIN_PX to spare. An
    object that reaches an image border is carved only where the border does not cut it, so a
    benchmark whose objects spread or fly would score the part in view only.
    """
    points = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    k = cameras.intrinsics
    focal = max(k.K[0, 0], k.K[1, 1])

    def poses(scale: float) -> list[np.ndarray]:
        moved = [T.copy() for T in cameras.poses]
        for T in moved:
            T[:3, 3] = cameras.target + scale * (T[:3, 3] - cameras.target)
        return moved

    def inside(scale: float) -> bool:
        for T in poses(scale):
            c = (points - T[:3, 3]) @ T[:3, :3]
            if np.any(c[:, 2] <= radius):
                return False
            uv = k.project(c)
            pad = FIT_MARGIN_PX + focal * radius / (c[:, 2] - radius)
            if (np.any(uv[:, 0] - pad < 0) or np.any(uv[:, 0] + pad > k.width - 1)
                    or np.any(uv[:, 1] - pad < 0) or np.any(uv[:, 1] + pad > k.height - 1)):
                return False
        return True

    lo, hi = 1.0, FIT_MAX_SCALE
    if inside(lo):
        return cameras
    if not inside(hi):
        _LOG.warning("fit_motion: the objects leave the views even with the cameras %.0fx as far from "
                     "look_at; recording at that distance", FIT_MAX_SCALE)
        lo = hi
    while hi / lo > 1.01:
        mid = math.sqrt(lo * hi)
        lo, hi = (lo, mid) if inside(mid) else (mid, hi)
    _LOG.info("fit_motion: cameras moved to %.2fx their distance from look_at to keep every object in view", hi)
    return replace(cameras, poses=poses(hi))


def simulate(layout: Layout, n_frames: int, progress: Progress | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """Particle positions (n_frames + 1, N, 3) float32 at the frame times, and the sim settings.

    The domain's walls are not part of the scene: when objects come within the wall cells of
    the grid (where the walls would stop them), the domain is widened to cover everywhere they
    went, plus twice the last margin, and the scene simulated again; after ``WALL_RETRIES``
    widenings it is an error.
    """
    spec, sim = layout.spec, layout.spec.simulation
    points = layout.x
    if spec.gripper is not None:
        reach = max(spec.gripper.size) * 2
        points = np.concatenate([points, spec.gripper.positions - reach, spec.gripper.positions + reach])
    margin = sim.margin
    for attempt in range(WALL_RETRIES + 1):
        simulator, config, substeps, dt = _simulator(layout, points, margin)
        _LOG.info("simulating %d frames x %d substeps (dt %.3g s) of %d particles on %s",
                  n_frames, substeps, dt, len(layout.x), simulator.device)
        report = None if progress is None else (lambda frame: progress("simulate", frame, n_frames, "frame"))
        trajectory = simulator.rollout(n_frames, progress=report)
        x = trajectory[:, 0]
        if not reaches_walls(x, simulator.lo, simulator.hi, sim.dx):
            break
        if attempt == WALL_RETRIES:
            raise ValueError("simulation: the objects keep reaching the walls of the domain after "
                             f"{WALL_RETRIES} widenings; raise simulation.margin")
        # cover where the objects went, and a margin (doubling: spreading material goes on
        # spreading) more on every side
        points = np.concatenate([points, x.reshape(-1, 3)])
        margin *= 2
        _LOG.info("objects reached the domain walls; widening the domain to where they went and "
                  "simulating again")
    ground = layout.ground
    settings = {
        "dx": sim.dx, "particle_spacing": sim.particle_spacing, "margin": margin, "cfl": sim.cfl,
        "max_speed": sim.max_speed, "device": simulator.device, "frame_dt": config.frame_dt,
        "substeps_per_frame": substeps, "substep_dt": dt, "domain_lo": simulator.lo,
        "domain_hi": simulator.hi, "simulated_frames": n_frames,
        "effects": {e.name: _effect_values(simulator, e.name, [s.name for s in e.params])
                    for e in config.effects},
        "ground": {"height": ground.height, "normal": list(ground.normal), "friction": ground.friction},
    }
    return trajectory[:, 0], settings


def _simulator(layout: Layout, points: np.ndarray, margin: float):
    """The scene's simulator on a domain ``margin`` metres around ``points`` and the floor."""
    spec, sim = layout.spec, layout.spec.simulation
    ground = layout.ground
    normal = np.asarray(ground.normal) / np.linalg.norm(ground.normal)
    lo, hi = domain_around(points, sim.dx, margin)
    # The floor must lie inside the grid: its lowest point over the domain's horizontal extent.
    corners = np.array([[x, y] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])])
    floor = float(np.min((ground.height - corners @ normal[:2]) / normal[2]))
    lo, hi = domain_around(points, sim.dx, margin, floor=floor)
    config = SimConfig(dx=sim.dx, lo=lo, hi=hi, frame_dt=1.0 / spec.cameras.fps, cfl=sim.cfl,
                       max_speed=sim.max_speed, ground=ground,
                       colliders=[layout.collider] if layout.collider else [],
                       effects=simulator_effects(spec.effects), device=sim.device)
    objects = [ObjectModel(o.name, o.family, dict(o.params), o.id) for o in spec.objects]
    particles = Particles(x=layout.x, volume=layout.volume, object_index=layout.object_index, v=layout.v)
    simulator = Simulator(objects, particles, config)
    substeps, dt = simulator.time_step()
    return simulator, config, substeps, dt


def _effect_values(simulator: Simulator, effect: str, names: list[str]) -> dict[str, Any]:
    """The values an effect ran with: vectors as lists, per-object values by object name."""
    values = {}
    for name in names:
        value = simulator.params.get(f"{effect}.{name}")[0]
        if simulator.params.spec(f"{effect}.{name}").per_object:
            value = dict(zip([o.name for o in simulator.objects], value.tolist(), strict=True))
        values[name] = value
    return values


def _pose_matrix(position: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    T[:3, 3] = position
    return T


def _at(positions: np.ndarray, frame: float) -> np.ndarray:
    """Positions at a fractional frame index, linear between frames, held outside the run."""
    frame = min(max(frame, 0.0), len(positions) - 1.0)
    i = min(int(math.floor(frame)), len(positions) - 2)
    w = frame - i
    return positions[i] if w < 1e-9 else (1.0 - w) * positions[i] + w * positions[i + 1]


def render_cameras(layout: Layout, positions: np.ndarray, offsets: dict[str, float],
                   rng: np.random.Generator, progress: Progress | None = None) -> dict[str, Camera]:
    """Every camera's frames 0..n_frames of the simulated ``positions`` (see the module docstring)."""
    spec = layout.spec
    cams, fps = spec.cameras, spec.cameras.fps
    spacing = spec.simulation.particle_spacing
    floor = Floor(layout.ground.height, layout.ground.normal, spec.ground.half_size)
    labels = np.array([spec.objects[k].id for k in layout.object_index])
    albedo = layout.albedo
    if spec.gripper is not None:
        grip = gripper_points(spec.gripper, spacing)
        labels = np.concatenate([labels, np.zeros(len(grip), dtype=labels.dtype)])
        albedo = np.concatenate([albedo, np.tile(spec.gripper.color, (len(grip), 1))])

    def splats(frame: float) -> Splats:
        x = _at(positions, frame)
        if spec.gripper is not None:
            position, quaternion = layout.collider.pose(frame / fps)
            x = np.concatenate([x, grip @ Rotation.from_quat(quaternion).as_matrix().T + position])
        return Splats(x, labels, albedo, surface_normals(x, labels, spacing), SPLAT_RADIUS * spacing)

    frames: dict[str, list[Frame]] = {name: [] for name in cams.names}
    total, done = (spec.n_frames + 1) * len(cams.names), 0
    for k in range(spec.n_frames + 1):
        shared = splats(float(k))
        for name, pose in zip(cams.names, cams.poses, strict=True):
            view = splats(k + offsets[name] * fps) if name in offsets else shared
            rgb, mask, depth = render_view(cams.intrinsics, pose, view, floor)
            frames[name].append(Frame(spec.stamp_ns(k), *_add_noise(layout, rgb, mask, depth, rng)))
            done += 1
            if progress is not None:
                progress("render", done, total, "image")
    return {name: Camera(name, cams.intrinsics, pose, frames[name])
            for name, pose in zip(cams.names, cams.poses, strict=True)}


def _add_noise(layout: Layout, rgb: np.ndarray, mask: np.ndarray, depth: np.ndarray,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    spec = layout.spec
    if spec.noise.rgb_std > 0:
        rgb = np.clip(rgb + rng.normal(0.0, spec.noise.rgb_std, rgb.shape), 0, 255).round().astype(np.uint8)
    if spec.noise.depth_std > 0:
        depth = (depth + rng.normal(0.0, spec.noise.depth_std, depth.shape)).astype(np.float32)
    mask = add_mask_noise(mask, spec.effects, len(spec.objects), rng)
    return rgb, mask, depth if spec.cameras.depth else None


def ground_truth_document(layout: Layout, settings: dict[str, Any], seed: int) -> dict[str, Any]:
    """Everything ground_truth.yaml says about a recording (see ``ground_truth``)."""
    spec = layout.spec
    units = {p.name: p.unit for p in MATERIAL_PARAMS} | {p.name: p.unit for p in GROUND_PARAMS}
    units |= {f"{name}.{p.name}": p.unit for name, effect in BUILTIN_EFFECTS.items() for p in effect.params}
    objects = []
    for obj, body in zip(spec.objects, layout.bodies, strict=True):
        objects.append({
            "id": obj.id, "name": obj.name, "family": obj.family, "params": obj.params,
            "declared_params": obj.declared_params, "declared_family": obj.declared_family,
            "shape": obj.shape, "size": obj.size,
            "position": obj.position, "orientation": obj.orientation, "velocity": obj.velocity,
            "angular_velocity": obj.angular_velocity, "color": obj.color, "texture": obj.texture,
            "particles": len(body.rest), "particle_volume": body.volume,
        })
    gripper = None
    if spec.gripper is not None:
        g = spec.gripper
        gripper = {"shape": g.shape, "size": g.size, "friction": g.friction, "times": g.times,
                   "positions": g.positions, "orientations": g.orientations}
    cams = spec.cameras
    return {
        "scene": spec.name, "scene_file": spec.source, "seed": seed,
        "frames": {"count": spec.n_frames + 1, "fps": cams.fps, "start_stamp_ns": spec.start_stamp_ns},
        "units": units,
        "objects": objects,
        "effects": [effect.ground_truth() for effect in spec.effects],
        "ground": {**settings["ground"], "half_size": spec.ground.half_size},
        "gripper": gripper,
        "cameras": {"names": cams.names, "placement": cams.placement, "width": cams.intrinsics.width,
                    "height": cams.intrinsics.height, "K": cams.intrinsics.K, "depth": cams.depth,
                    "T_world_optical": dict(zip(cams.names, cams.poses, strict=True))},
        "noise": {"rgb_std": spec.noise.rgb_std, "depth_std": spec.noise.depth_std},
        "simulation": settings,
        "render": {"splat_radius": SPLAT_RADIUS * spec.simulation.particle_spacing,
                   "surface": "union of balls of splat_radius around the particles"},
    }
