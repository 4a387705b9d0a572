"""Scene files shared by the synthetic-recorder tests (CPU-sized: a few hundred particles)."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import yaml

FPS = 10.0
CAM0 = {"name": "cam0", "position": [0.45, -0.3, 0.3], "look_at": [0.0, 0.0, 0.05]}
PAIR = {
    "name": "test_pair",
    "duration": 0.5,
    "objects": [
        {"name": "clay", "shape": "box", "size": [0.14, 0.12, 0.05], "position": [0.0, 0.0, 0.025],
         "family": "plastic", "params": {"E": 5.0e4, "yield_stress": 2.0e3, "density": 1200},
         "declared_params": ["density"], "color": [40, 170, 60], "texture": "checker"},
        {"name": "ball", "shape": "sphere", "radius": 0.045, "position": [-0.02, 0.0, 0.12],
         "velocity": [0.3, 0.0, -0.5], "family": "elastic", "params": {"E": 4.0e4},
         "color": [210, 40, 35]},
    ],
    "gripper": {"shape": "sphere", "radius": 0.025, "trajectory": [
        {"t": 0.0, "position": [0.15, 0.0, 0.04]}, {"t": 0.5, "position": [0.08, 0.0, 0.04]}]},
    "cameras": {
        "placement": "explicit",
        "poses": [
            CAM0,
            {"name": "cam1", "position": [-0.35, -0.4, 0.25], "look_at": [0.0, 0.0, 0.05]},
            {"name": "top", "position": [0.0, 0.0, 0.6], "look_at": [0.0, 0.0, 0.0]},
            {**CAM0, "name": "late"},
        ],
        "resolution": [64, 48],
        "horizontal_fov": 0.9,
        "fps": FPS,
    },
    "effects": [
        {"type": "wind", "a": [0.5, 0.0, 0.0], "declared": True},
        {"type": "floor_friction", "friction": 0.8, "declared": True},
        {"type": "camera_time_offset", "camera": "late", "offset": 1.0 / FPS, "declared": True},
        {"type": "drag", "coefficient": 1.5, "declared": False},
    ],
    "simulation": {"dx": 0.03, "margin": 0.1},
}
"""A ball dropped onto a clay slab while a gripper pushes the slab, seen by four cameras.

``top`` looks straight down, so the ball hides the middle of the slab; ``late`` shares cam0's
pose and runs one frame ahead. Wind and floor friction are declared, air drag is not.
"""


def pair_scene(**changes: object) -> dict:
    """A deep copy of PAIR with top-level keys replaced."""
    scene = copy.deepcopy(PAIR)
    scene.update(copy.deepcopy(changes))
    return scene


def write_scene(directory: Path, scene: dict, name: str = "scene.yaml") -> Path:
    """Write ``scene`` as a scene file in ``directory``; return its path."""
    path = Path(directory) / name
    path.write_text(yaml.safe_dump(scene, sort_keys=False), encoding="utf-8")
    return path


def record_scene(directory: Path, scene: dict, name: str, seed: int = 0) -> Path:
    """Record ``scene`` into the bag ``directory/name`` with the project's recorder."""
    from mosiv_ros.synth.recorder import record
    from mosiv_ros.synth.scene_file import read_scene_file

    return record(read_scene_file(write_scene(directory, scene, f"{name}.yaml")), Path(directory) / name,
                  seed=seed)


DROP = {
    "name": "test_drop",
    "duration": 0.8,
    "objects": [
        {"name": "jelly", "shape": "box", "size": [0.08, 0.08, 0.08], "position": [0.0, 0.0, 0.14],
         "velocity": [0.3, 0.0, -0.4], "family": "elastic", "params": {"E": 2.0e4, "nu": 0.3},
         "color": [210, 40, 35]},
    ],
    "cameras": {"placement": "ring", "count": 2, "radius": 0.5, "height": 0.3,
                "look_at": [0.05, 0.0, 0.05], "resolution": [64, 48], "horizontal_fov": 0.9,
                "fps": FPS},
    "simulation": {"dx": 0.03, "margin": 0.1},
}
"""One soft cube thrown at the floor, two cameras, 9 frames: the pipeline's smallest input."""

FAST_PARAMS = {
    "lifting_node": {"ros__parameters": {"particle_spacing": 0.015}},
    "identify_node": {"ros__parameters": {
        "curriculum": {"horizons": [0], "iterations": 1}, "search": {"rounds": 1, "starts": 1},
        "uncertainty": False, "loss": {"silhouette_weight": 0.0}}},
    "prediction_node": {"ros__parameters": {"horizon": 0.5}},
}
"""Node parameters for a fit of a few seconds: the plumbing, not the accuracy, is under test."""


def gripper_sweep(scene, centre, stamp_ns: int):
    """``scene`` with a declared 3 cm sphere gripper, and its poses sweeping through ``centre``.

    Along +x from -15 to +15 cm in 0.3 s from ``stamp_ns``: (scene, [(stamp_ns, T_world)]).
    """
    swept = dataclasses.replace(scene, gripper={"shape": "sphere", "radius": 0.03})
    poses = []
    for k, dx in enumerate(np.linspace(-0.15, 0.15, 4)):
        T = np.eye(4)
        T[:3, 3] = np.asarray(centre) + [dx, 0.0, 0.0]
        poses.append((stamp_ns + round(k * 0.1e9), T))
    return swept, poses
