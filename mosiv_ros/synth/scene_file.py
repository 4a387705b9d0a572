"""Scene files of the synthetic recorder: the documented YAML schema, parsed and checked.

What it is for: reading a scene description (objects, ground, gripper, cameras, duration,
noise, effects, simulation settings) into a ``SceneSpec``, rejecting every bad value with a
``SceneError`` that names the field (``objects[1].radius: must be positive, got -0.1``).
Checks that need geometry (objects overlapping at t = 0, below the floor, cameras that see no
object) are made by ``layout.lay_out``, which ``recorder.record`` runs first.
What it is not for: the bag's scene declaration (``mosiv_ros.io.scene``), which the recorder
derives from a SceneSpec.

Schema (SI units throughout, radians for angles; the one exception is a sand's friction angle,
given in degrees as ``friction_angle_deg``). Unknown keys are errors everywhere::

    version: 1                       # optional; only 1 is understood
    name: elastic_on_plastic         # optional, default: the file name
    duration: 2.0                    # s; frames at t = 0, 1/fps, ..., duration
    start_stamp_ns: 1700000000000000000   # optional, stamp of frame 0
    objects:                         # 1..K, mask ids in list order
      - name: ball                   # unique
        shape: sphere                # box | sphere | cylinder | torus | mesh, with its size keys:
        radius: 0.05                 #   sphere: radius; cylinder: radius, height (along local z);
                                     #   box: size [x, y, z] (full edge lengths);
                                     #   torus: major_radius, minor_radius (ring in local xy);
                                     #   mesh: file (watertight, relative to this file), scale
        position: [0, 0, 0.3]        # m, world position of the shape's centre (mesh: its origin)
        orientation: [0, 0, 0, 1]    # optional quaternion x, y, z, w (world from object)
        velocity: [0.5, 0, -1]       # optional, m/s
        angular_velocity: [0, 0, 3]  # optional, rad/s about the centre
        family: elastic              # elastic | plastic | sand | fluid
        params: {E: 5.0e4, nu: 0.3}  # optional: the family's parameters (simulator defaults
                                     #   otherwise); sand: friction_angle_deg instead of radians
        declared_params: [density]   # optional: parameters the bag's declaration tells
        declared_family: true        # optional: false = the declaration leaves the family out
        color: [210, 40, 35]         # optional RGB 0..255 (default: a palette colour by id)
        texture: checker             # optional: none (default) | checker, a darker colour on
        texture_scale: 0.03          #   rest-frame cubes of this side (m), moving with the material
    ground: {height: 0.0, half_size: 1.2}   # optional; half_size only bounds the rendered floor
    gripper:                         # optional kinematic collider, published on /gripper/pose
      shape: sphere                  # sphere (radius) | box (half_extents) | capsule (radius,
      radius: 0.02                   #   half_length along local z)
      friction: 0.5                  # optional
      color: [90, 90, 100]           # optional
      trajectory:                    # keyframes, linear in between (slerp for orientations)
        - {t: 0.0, position: [0.2, 0, 0.1], orientation: [0, 0, 0, 1]}
    cameras:
      placement: ring                # ring | hemisphere | explicit
      count: 3                       # ring, hemisphere
      radius: 0.8                    # ring: horizontal distance to look_at; hemisphere: distance
      height: 0.5                    # ring: world z of the cameras
      start_angle: 0.3               # ring: azimuth of cam0 (rad), optional
      min_elevation: 0.3             # hemisphere (rad above look_at's horizontal)
      max_elevation: 1.3             # hemisphere
      look_at: [0, 0, 0.05]          # ring, hemisphere
      fit_motion: false              # ring, hemisphere: after the simulation, move the cameras
                                     #   back along their lines of sight until every object
                                     #   stays inside every image in every frame
      poses:                         # explicit: one entry per camera
        - {name: top, position: [0, 0, 1], look_at: [0, 0, 0]}
      resolution: [96, 72]           # width, height in pixels
      horizontal_fov: 0.9            # rad; or fx (and optionally fy, cx, cy) in pixels
      fps: 15
      depth: true                    # optional: publish depth images
    noise: {rgb_std: 2.0, depth_std: 0.001}  # optional: Gaussian noise, 0..255 units and m
    effects:                         # optional: see mosiv_ros.synth.effects for the types
      - {type: drag, coefficient: 2.0, declared: false}
    simulation:                      # optional
      dx: 0.02                       # grid spacing, m
      particle_spacing: 0.01         # default dx / 2
      margin: 0.15                   # m of grid around the objects' (and gripper's) start
      cfl: 0.4
      max_speed: 5.0                 # m/s the time step allows for on top of wave speeds
      device: auto                   # auto | cpu | cuda:0
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mosiv_ros.io.errors import SceneError, shown
from mosiv_ros.io.fields import Fields
from mosiv_ros.io.recording import CameraIntrinsics
from mosiv_ros.io.scene import FAMILIES, DeclaredGripper, load_yaml, read_scene_text
from mosiv_ros.sim import FAMILY_PARAMS, MATERIAL_PARAMS, Collider
from mosiv_ros.synth import cameras as rig
from mosiv_ros.synth.effects import EffectSpec, check_unique, parse_effect

SHAPES = ("box", "sphere", "cylinder", "torus", "mesh")
PLACEMENTS = ("ring", "hemisphere", "explicit")
TEXTURES = ("none", "checker")
DEFAULT_START_NS = 1_700_000_000_000_000_000
PALETTE = ([210.0, 40.0, 35.0], [40.0, 170.0, 60.0], [45.0, 70.0, 200.0], [220.0, 170.0, 30.0],
           [150.0, 60.0, 190.0], [30.0, 170.0, 180.0])
"""Default object colours, by mask id."""
_SPECS = {spec.name: spec for spec in MATERIAL_PARAMS}

# What one recording may ask for, checked before anything is allocated (the scene file's
# fields are named in the error). docs/limits.md lists them.
MAX_FRAMES = 10_000
"""Most frames of a recording: duration x cameras.fps + 1."""
MAX_IMAGE_PIXELS = 4096 * 4096
"""Most pixels of one camera image: cameras.resolution width x height."""
MAX_PARTICLES = 4_000_000
"""Most particles the objects may be filled with (simulation.particle_spacing), counted on the
lattice each shape is cut from."""
MAX_RECORDING_BYTES = 8 * 2**30
"""Most bytes a recording may hold before it is written: every camera's images (RGB, mask and
depth) and the particles' paths (float32), all of which stay in memory until the end."""
BYTES_PER_PIXEL = 3 + 2 + 4
"""RGB, a mono16 mask (the wider one) and float32 depth, per pixel of a frame."""


@dataclass
class ObjectSpec:
    """One object: mask id, shape and size, initial pose and motion, material, appearance."""

    id: int
    name: str
    shape: str
    size: dict[str, Any]
    position: np.ndarray
    orientation: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    family: str
    params: dict[str, float]
    declared_params: list[str]
    color: np.ndarray
    texture: str = "none"
    texture_scale: float = 0.03
    declared_family: bool = True


@dataclass
class GroundSpec:
    """The floor's height (m) and the half size of its rendered square (m)."""

    height: float = 0.0
    half_size: float = 1.2


@dataclass
class GripperSpec:
    """A kinematic collider: shape, size (as ``sim.Collider`` takes it), keyframes."""

    shape: str
    size: tuple[float, ...]
    friction: float
    color: np.ndarray
    times: np.ndarray
    positions: np.ndarray
    orientations: np.ndarray

    def declaration(self) -> DeclaredGripper:
        """The gripper's entry in the bag's scene declaration: its shape and size."""
        return DeclaredGripper(self.shape, self.size)


@dataclass
class CameraSpec:
    """The rig: camera names, poses (T_world_optical), one intrinsics, frame rate, depth."""

    names: list[str]
    poses: list[np.ndarray]
    intrinsics: CameraIntrinsics
    fps: float
    depth: bool
    placement: str
    target: np.ndarray | None = None
    """The point ring and hemisphere cameras look at (None for explicit poses)."""
    fit_motion: bool = False
    """Move the cameras back from ``target`` after the simulation until every object stays in
    every image (``synth.recorder.fit_views``)."""


@dataclass
class NoiseSpec:
    """Gaussian sensor noise: RGB standard deviation (0..255 units), depth (m)."""

    rgb_std: float = 0.0
    depth_std: float = 0.0


@dataclass
class SimulationSpec:
    """Simulator settings (see ``mosiv_ros.sim.SimConfig``)."""

    dx: float = 0.02
    particle_spacing: float = 0.01
    margin: float = 0.15
    cfl: float = 0.4
    max_speed: float = 5.0
    device: str = "auto"


@dataclass
class SceneSpec:
    """A parsed scene file (see the module docstring)."""

    name: str
    source: str
    duration: float
    start_stamp_ns: int
    objects: list[ObjectSpec]
    ground: GroundSpec
    gripper: GripperSpec | None
    cameras: CameraSpec
    effects: list[EffectSpec] = field(default_factory=list)
    noise: NoiseSpec = field(default_factory=NoiseSpec)
    simulation: SimulationSpec = field(default_factory=SimulationSpec)

    @property
    def n_frames(self) -> int:
        """Frames recorded after the first: the recording has n_frames + 1 frames."""
        return max(1, round(self.duration * self.cameras.fps))

    def stamp_ns(self, frame: int) -> int:
        """Stamp of frame ``frame``."""
        return self.start_stamp_ns + round(frame * 1e9 / self.cameras.fps)


def read_scene_file(path: str | Path) -> SceneSpec:
    """Parse the scene file at ``path`` (no geometric checks: ``layout.lay_out`` makes them)."""
    return parse_scene_file(read_scene_text(Path(path)), source=str(path), base_dir=Path(path).parent)


def parse_scene_file(text: str, source: str = "<string>", base_dir: Path | None = None) -> SceneSpec:
    """Parse scene-file YAML ``text``; mesh files are relative to ``base_dir`` (default cwd)."""
    try:
        document = load_yaml(text)
    except yaml.YAMLError as exc:
        raise SceneError("", f"invalid YAML: {exc}", source) from None
    try:
        return _scene(Fields(document, ""), source, base_dir or Path.cwd())
    except SceneError as exc:
        raise SceneError(exc.field, exc.problem, source) from None


def _scene(top: Fields, source: str, base_dir: Path) -> SceneSpec:
    version = top.get("version", 1)
    if version != 1:
        raise SceneError("version", f"unsupported scene file version {shown(version)} (expected 1)")
    name = top.string("name", Path(source).stem if source != "<string>" else "scene")
    duration = top.number("duration", positive=True)
    start = top.get("start_stamp_ns", DEFAULT_START_NS)
    if not isinstance(start, int) or isinstance(start, bool) or start < 0:
        raise SceneError("start_stamp_ns", f"expected a non-negative integer, got {shown(start)}")
    entries = top.items("objects")
    if not entries:
        raise SceneError("objects", "a scene needs at least one object")
    objects = [_object(Fields(raw, where), i + 1, base_dir) for i, (where, raw) in enumerate(entries)]
    names = [o.name for o in objects]
    for index, obj in enumerate(objects):
        if names.index(obj.name) != index:
            raise SceneError(f"objects[{index}].name",
                             f"name {shown(obj.name)} already used by objects[{names.index(obj.name)}]")
    ground_fields = top.section("ground", {})
    ground = GroundSpec(ground_fields.number("height", 0.0),
                        ground_fields.number("half_size", GroundSpec.half_size, positive=True))
    ground_fields.done()
    gripper = _gripper(top.section("gripper")) if top.has("gripper") else None
    cameras = _cameras(top.section("cameras"))
    effects = [parse_effect(raw, where, names, cameras.names) for where, raw in top.items("effects", [])]
    check_unique(effects)
    noise_fields = top.section("noise", {})
    noise = NoiseSpec(noise_fields.number("rgb_std", 0.0, lower=0.0, upper=255.0),
                      noise_fields.number("depth_std", 0.0, lower=0.0, upper=1.0))
    noise_fields.done()
    simulation = _simulation(top.section("simulation", {}))
    top.done()
    spec = SceneSpec(name, source, duration, start, objects, ground, gripper, cameras, effects, noise,
                     simulation)
    if duration * cameras.fps + 1 > MAX_FRAMES:
        raise SceneError("duration", f"{duration:g} s at cameras.fps {cameras.fps:g} is "
                         f"{duration * cameras.fps + 1:.3g} frames, more than {MAX_FRAMES}")
    return spec


def check_recording_size(spec: SceneSpec, particles: int) -> None:
    """SceneError naming the scene file if its recording would hold more than MAX_RECORDING_BYTES.

    ``particles``: how many the laid-out objects have. Made before the simulation and rendering.
    """
    frames, cameras = spec.n_frames + 1, len(spec.cameras.names)
    k = spec.cameras.intrinsics
    images = frames * cameras * k.width * k.height * (BYTES_PER_PIXEL - (0 if spec.cameras.depth else 4))
    paths = frames * particles * 3 * 4
    if images + paths > MAX_RECORDING_BYTES:
        field = "cameras.resolution" if images >= paths else "simulation.particle_spacing"
        raise SceneError(field, f"the recording would hold {(images + paths) / 2**30:.3g} GiB: images "
                         f"{images / 2**30:.3g} GiB ({frames} frames x {cameras} cameras x {k.width} x "
                         f"{k.height} pixels) and particle paths {paths / 2**30:.3g} GiB ({particles} "
                         f"particles), more than {MAX_RECORDING_BYTES / 2**30:g} GiB (shorten duration, "
                         "lower cameras.fps or cameras.resolution, or raise simulation.particle_spacing)",
                         spec.source)


def _object(f: Fields, object_id: int, base_dir: Path) -> ObjectSpec:
    name = f.string("name")
    if "/" in name or " " in name:
        raise SceneError(f.path("name"), f"must not contain '/' or spaces, got {shown(name)}")
    shape = f.string("shape", choices=SHAPES)
    size = _size(f, shape, base_dir)
    family = f.string("family", choices=FAMILIES)
    params = _params(f.section("params", {}), family)
    allowed = tuple(_user_name(p) for p in FAMILY_PARAMS[family])
    declared = f.get("declared_params", [])
    if not isinstance(declared, list):
        raise SceneError(f.path("declared_params"), f"expected a list, got {shown(declared)}")
    for i, key in enumerate(declared):
        if key not in allowed:
            raise SceneError(f"{f.path('declared_params')}[{i}]",
                             f"{shown(key)} is not a parameter of {family} (expected one of {', '.join(allowed)})")
    orientation = f.vector("orientation", 4, [0.0, 0.0, 0.0, 1.0])
    if not np.any(orientation):
        raise SceneError(f.path("orientation"), "must be a non-zero quaternion x, y, z, w")
    spec = ObjectSpec(
        id=object_id,
        name=name,
        shape=shape,
        size=size,
        position=f.vector("position", 3),
        orientation=orientation / np.linalg.norm(orientation),
        velocity=f.vector("velocity", 3, [0.0, 0.0, 0.0]),
        angular_velocity=f.vector("angular_velocity", 3, [0.0, 0.0, 0.0]),
        family=family,
        params=params,
        declared_params=["friction_angle" if k == "friction_angle_deg" else k for k in declared],
        color=_color(f, "color", PALETTE[(object_id - 1) % len(PALETTE)]),
        texture=f.string("texture", "none", choices=TEXTURES),
        texture_scale=f.number("texture_scale", ObjectSpec.texture_scale, positive=True),
        declared_family=f.boolean("declared_family", True),
    )
    f.done(f" for a {shape}")
    return spec


def _size(f: Fields, shape: str, base_dir: Path) -> dict[str, Any]:
    if shape == "box":
        return {"size": f.vector("size", 3, positive=True)}
    if shape == "sphere":
        return {"radius": f.number("radius", positive=True)}
    if shape == "cylinder":
        return {"radius": f.number("radius", positive=True), "height": f.number("height", positive=True)}
    if shape == "torus":
        major = f.number("major_radius", positive=True)
        minor = f.number("minor_radius", positive=True)
        if minor >= major:
            raise SceneError(f.path("minor_radius"), f"must be below major_radius ({major}), got {minor}")
        return {"major_radius": major, "minor_radius": minor}
    path = base_dir / f.string("file")
    if not path.is_file():
        raise SceneError(f.path("file"), f"no such mesh file: {path}")
    return {"file": path, "scale": f.number("scale", 1.0, positive=True)}


def _user_name(param: str) -> str:
    return "friction_angle_deg" if param == "friction_angle" else param


def _params(f: Fields, family: str) -> dict[str, float]:
    """Every parameter of ``family`` in SI units (radians): given values, else defaults."""
    params = {}
    for name in FAMILY_PARAMS[family]:
        spec = _SPECS[name]
        if name == "friction_angle":
            degrees = f.number("friction_angle_deg", math.degrees(spec.default),
                               lower=math.degrees(spec.lower), upper=math.degrees(spec.upper))
            params[name] = math.radians(degrees)
        else:
            params[name] = f.number(name, spec.default, lower=spec.lower, upper=spec.upper)
    f.done(f" for {family}")
    return params


def _color(f: Fields, key: str, default: list[float]) -> np.ndarray:
    color = f.vector(key, 3, default)
    if np.any(color < 0) or np.any(color > 255):
        raise SceneError(f.path(key), f"RGB values must lie in 0..255, got {color.tolist()}")
    return color


def _gripper(f: Fields) -> GripperSpec:
    collider = DeclaredGripper.read(f)
    shape = collider.shape
    friction = Collider.friction if collider.friction is None else collider.friction
    color = _color(f, "color", [90.0, 90.0, 100.0])
    keys = f.items("trajectory")
    if not keys:
        raise SceneError(f.path("trajectory"), "needs at least one keyframe")
    times, positions, orientations = [], [], []
    for where, raw in keys:
        key = Fields(raw, where)
        times.append(key.number("t", lower=0.0))
        positions.append(key.vector("position", 3))
        q = key.vector("orientation", 4, [0.0, 0.0, 0.0, 1.0])
        if not np.any(q):
            raise SceneError(key.path("orientation"), "must be a non-zero quaternion x, y, z, w")
        orientations.append(q / np.linalg.norm(q))
        key.done()
        if len(times) > 1 and times[-1] <= times[-2]:
            raise SceneError(key.path("t"), f"keyframe times must increase, got {times[-2]} then {times[-1]}")
    f.done(f" for a {shape}")
    return GripperSpec(shape, collider.size, friction, color, np.array(times), np.array(positions),
                       np.array(orientations))


def _cameras(f: Fields) -> CameraSpec:
    placement = f.string("placement", choices=PLACEMENTS)
    target, fit_motion = None, False
    if placement == "explicit":
        names, poses = [], []
        for where, raw in f.items("poses"):
            entry = Fields(raw, where)
            names.append(entry.string("name", f"cam{len(names)}"))
            position, target = entry.vector("position", 3), entry.vector("look_at", 3)
            if np.allclose(position, target):
                raise SceneError(entry.path("look_at"), "must differ from the camera's position")
            poses.append(rig.look_at(position, target))
            entry.done()
        if not poses:
            raise SceneError(f.path("poses"), "needs at least one camera")
        if len(set(names)) != len(names):
            raise SceneError(f.path("poses"), f"camera names must be unique, got {names}")
    else:
        count = f.integer("count")
        target = f.vector("look_at", 3)
        radius = f.number("radius", positive=True)
        if placement == "ring":
            poses = rig.ring_poses(count, radius, f.number("height"), target, f.number("start_angle", 0.0))
        else:
            low = f.number("min_elevation", 0.3, lower=-math.pi / 2, upper=math.pi / 2)
            high = f.number("max_elevation", 1.2, lower=low, upper=math.pi / 2)
            poses = rig.hemisphere_poses(count, radius, target, low, high)
        names = [f"cam{i}" for i in range(count)]
        fit_motion = f.boolean("fit_motion", False)
    width, height_px = (int(v) for v in f.vector("resolution", 2, positive=True))
    if width < 8 or height_px < 8:
        raise SceneError(f.path("resolution"), f"must be at least 8 x 8 pixels, got {width} x {height_px}")
    if f.has("fx"):
        try:
            intrinsics = rig.pinhole(width, height_px, fx=f.number("fx", positive=True),
                                     fy=f.number("fy", positive=True) if f.has("fy") else None,
                                     cx=f.number("cx") if f.has("cx") else None,
                                     cy=f.number("cy") if f.has("cy") else None)
        except ValueError as exc:  # the calibration check of CameraIntrinsics (k[2] is cx, ...)
            raise SceneError(f.where, str(exc)) from None
    else:
        fov = f.number("horizontal_fov", 0.9, lower=0.05, upper=3.0)
        intrinsics = rig.pinhole(width, height_px, horizontal_fov=fov)
    if width * height_px > MAX_IMAGE_PIXELS:
        raise SceneError(f.path("resolution"), f"{width} x {height_px} is {width * height_px:.3g} pixels, "
                         f"more than {MAX_IMAGE_PIXELS} per camera image")
    spec = CameraSpec(names, poses, intrinsics, f.number("fps", positive=True), f.boolean("depth", True),
                      placement, target, fit_motion)
    f.done(f" for {placement} placement")
    return spec


def _simulation(f: Fields) -> SimulationSpec:
    dx = f.number("dx", SimulationSpec.dx, positive=True)
    spec = SimulationSpec(
        dx=dx,
        particle_spacing=f.number("particle_spacing", dx / 2, positive=True),
        margin=f.number("margin", SimulationSpec.margin, lower=0.0),
        cfl=f.number("cfl", SimulationSpec.cfl, positive=True, upper=1.0),
        max_speed=f.number("max_speed", SimulationSpec.max_speed, lower=0.0),
        device=f.string("device", "auto"),
    )
    if spec.particle_spacing > dx:
        raise SceneError(f.path("particle_spacing"), f"must not exceed dx ({dx}), got {spec.particle_spacing}")
    f.done()
    return spec
