"""A benchmark suite of synthetic two-object recordings, in the spirit of MOSIV's synthetic set.

What it is for: generating scene files (and, by default, their recordings) for pairs of objects
drawn from a set of shapes, over every pairing of the four material families, either colliding
(one thrown at the other) or stacked (one resting on the other), seen by several cameras.
Material parameters are jittered per scene (seeded) around family defaults, so that a method
cannot score by predicting the defaults. Sizes: ``tiny`` (CPU, CI: the 10 unordered family
pairs, small images, a few frames) and ``full`` (GPU: the 16 ordered pairs x both interactions
x two shape pairs, 6 views, 2 s at 30 fps, the cameras moved back after the simulation until
every object stays in every view: ``cameras.fit_motion``).
What it is not for: recording (``recorder``) or evaluating (the evaluation code reads each
bag's ground-truth sidecars).

Output: ``OUT/scenes/<name>.yaml``, ``OUT/<name>/`` (a bag with its sidecars) and
``OUT/suite.yaml`` (the index: each scene's name, families, shapes, interaction, files).
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mosiv_ros.io.files import check_new_path
from mosiv_ros.io.scene import FAMILIES
from mosiv_ros.progress import Progress
from mosiv_ros.synth.layout import lay_out
from mosiv_ros.synth.recorder import record
from mosiv_ros.synth.scene_file import read_scene_file

_LOG = logging.getLogger(__name__)

SHAPE_SET: dict[str, dict[str, Any]] = {  # at scale 1: (size keys, half height, footprint radius)
    "sphere": {"shape": "sphere", "radius": 0.045},
    "box": {"shape": "box", "size": [0.1, 0.08, 0.06]},
    "cylinder": {"shape": "cylinder", "radius": 0.04, "height": 0.08},
    "torus": {"shape": "torus", "major_radius": 0.045, "minor_radius": 0.02},
}
FAMILY_DEFAULTS: dict[str, dict[str, float]] = {
    "elastic": {"E": 5.0e4, "nu": 0.3, "density": 1000.0, "friction": 0.4},
    "plastic": {"E": 8.0e4, "nu": 0.3, "yield_stress": 2.0e3, "density": 1200.0, "friction": 0.5},
    "sand": {"E": 1.0e5, "nu": 0.3, "friction_angle_deg": 35.0, "density": 1600.0, "friction": 0.5},
    "fluid": {"bulk_modulus": 5.0e4, "viscosity": 0.5, "density": 1000.0, "friction": 0.1},
}
JITTER = {"E": 2.0, "yield_stress": 2.0, "bulk_modulus": 2.0, "viscosity": 3.0, "friction": 1.5,
          "friction_angle_deg": 1.2}
"""Per-scene factor range: a parameter is multiplied by f in [1/J, J], log-uniform."""
INTERACTIONS = ("collide", "stack")
COLORS = ([210.0, 40.0, 35.0], [45.0, 110.0, 210.0])


@dataclass(frozen=True)
class SuiteSize:
    """How large a suite is: which pairings, how many views, how long, how fine."""

    ordered_pairs: bool
    every_interaction: bool  # each pairing in both interactions, else in one, in turn
    shape_pairs: int
    cameras: int
    resolution: tuple[int, int]
    fps: float
    duration: float
    dx: float
    scale: float
    fit_views: bool  # cameras moved back after the simulation until every object stays in view


SIZES = {
    "tiny": SuiteSize(False, False, 1, 2, (48, 36), 10.0, 0.6, 0.03, 1.0, False),
    "full": SuiteSize(True, True, 2, 6, (256, 192), 30.0, 2.0, 0.01, 1.0, True),
}


def _extent(shape: dict[str, Any]) -> tuple[float, float]:
    """(half height, horizontal footprint radius) of a SHAPE_SET entry."""
    if shape["shape"] == "sphere":
        return shape["radius"], shape["radius"]
    if shape["shape"] == "box":
        return shape["size"][2] / 2, float(np.hypot(*shape["size"][:2])) / 2
    if shape["shape"] == "cylinder":
        return shape["height"] / 2, shape["radius"]
    return shape["minor_radius"], shape["major_radius"] + shape["minor_radius"]


def _scaled(name: str, scale: float) -> dict[str, Any]:
    return {k: (np.multiply(v, scale).tolist() if k != "shape" else v) for k, v in SHAPE_SET[name].items()}


def _params(family: str, rng: np.random.Generator) -> dict[str, float]:
    params = dict(FAMILY_DEFAULTS[family])
    for key, factor in JITTER.items():
        if key in params:
            params[key] = float(f"{params[key] * factor ** rng.uniform(-1.0, 1.0):.4g}")
    return params


def scene_document(name: str, families: tuple[str, str], shapes: tuple[str, str], interaction: str,
                   size: SuiteSize, rng: np.random.Generator) -> dict[str, Any]:
    """The scene file (as YAML data) of object A (``families[0]``) meeting object B on the floor."""
    a, b = _scaled(shapes[0], size.scale), _scaled(shapes[1], size.scale)
    (ha, ra), (hb, rb) = _extent(a), _extent(b)
    gap = size.dx / 4
    if interaction == "stack":
        pa, va = [0.0, 0.0, 2 * hb + ha + gap], [0.0, 0.0, 0.0]
    else:
        # thrown low at B (its centre about level with B's, rising 2 cm before it arrives), so
        # that it hits B rather than flies over a low one (a box, a torus)
        pa, va = [-(ra + rb + 0.05), 0.0, max(ha, hb) + gap + 0.01], [1.2, 0.0, 0.3]
    objects = []
    for label, family, shape, position, velocity, color in (
        ("a", families[0], a, pa, va, COLORS[0]), ("b", families[1], b, [0.0, 0.0, hb + gap], [0.0] * 3, COLORS[1])
    ):
        objects.append({"name": f"{label}_{family}", **shape, "position": position, "velocity": velocity,
                        "family": family, "params": _params(family, rng), "color": color, "texture": "checker"})
    reach = 2 * (hb + ha) + 0.1
    return {
        "name": name,
        "duration": size.duration,
        "objects": objects,
        "ground": {"height": 0.0, "half_size": 0.8},
        "cameras": {"placement": "hemisphere", "count": size.cameras, "radius": 3.2 * reach,
                    "look_at": [0.0, 0.0, hb], "min_elevation": 0.35, "max_elevation": 0.9,
                    "resolution": list(size.resolution), "horizontal_fov": 0.7, "fps": size.fps,
                    "fit_motion": size.fit_views},
        "simulation": {"dx": size.dx, "margin": 0.1},
    }


def suite_scenes(size_name: str, seed: int = 0) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(index entry, scene document) of every scene of the suite of size ``size_name``."""
    if size_name not in SIZES:
        raise ValueError(f"unknown suite size {size_name!r} (expected one of {', '.join(SIZES)})")
    size = SIZES[size_name]
    pairs = (list(itertools.product(FAMILIES, repeat=2)) if size.ordered_pairs
             else list(itertools.combinations_with_replacement(FAMILIES, 2)))
    shape_pairs = list(itertools.permutations(SHAPE_SET, 2))
    scenes = []
    for index, (families, variant) in enumerate(itertools.product(pairs, range(size.shape_pairs))):
        interactions = INTERACTIONS if size.every_interaction else INTERACTIONS[index % 2:index % 2 + 1]
        for interaction in interactions:
            shapes = shape_pairs[(index * size.shape_pairs + variant) % len(shape_pairs)]
            name = f"{families[0]}_{shapes[0]}__{families[1]}_{shapes[1]}__{interaction}"
            rng = np.random.default_rng([seed, len(scenes)])
            entry = {"name": name, "families": list(families), "shapes": list(shapes), "interaction": interaction}
            scenes.append((entry, scene_document(name, families, shapes, interaction, size, rng)))
    return scenes


def make_suite(out: str | Path, size_name: str, *, seed: int = 0, record_bags: bool = True,
               progress: Progress | None = None, record_progress: Progress | None = None) -> Path:
    """Write the suite's scene files (and record them) under the new directory ``out``.

    ``progress('scenes', done, total, 'scene')`` after each scene; ``record_progress`` goes to ``record``.
    """
    out = check_new_path(out)  # before any recording
    out.mkdir(parents=True)
    (out / "scenes").mkdir()
    scenes = suite_scenes(size_name, seed)
    index = []
    for done, (entry, document) in enumerate(scenes, start=1):
        scene_file = out / "scenes" / f"{entry['name']}.yaml"
        scene_file.write_text(yaml.safe_dump(document, sort_keys=False), encoding="utf-8")
        spec = read_scene_file(scene_file)
        entry = {**entry, "scene_file": str(scene_file.relative_to(out))}
        if record_bags:
            record(spec, out / entry["name"], seed=seed, progress=record_progress)
            entry["bag"] = entry["name"]
        else:
            lay_out(spec)  # the checks a recording would make
        index.append(entry)
        if progress is not None:
            progress("scenes", done, len(scenes), "scene")
    (out / "suite.yaml").write_text(yaml.safe_dump({"size": size_name, "seed": seed, "scenes": index},
                                                   sort_keys=False), encoding="utf-8")
    _LOG.info("wrote the %s suite (%d scenes) to %s", size_name, len(index), out)
    return out
