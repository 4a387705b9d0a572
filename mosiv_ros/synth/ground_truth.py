"""Ground-truth sidecars of a synthetic recording, inside the bag directory beside metadata.yaml.

What it is for: writing and reading ``ground_truth.yaml`` (every object parameter, every effect
with ``declared: true/false``, the simulator and renderer settings; DESIGN.md) and
``ground_truth_particles.npz`` (per-frame particle positions with their object ids). rosbag2
readers ignore both files; only evaluation code and tests read them. They never go into the bag.
What it is not for: deciding what they contain (``recorder`` does) or any bag I/O.

``ground_truth_particles.npz`` arrays: ``positions`` (F, N, 3) float32 metres in ``world`` at
the recorded frames, ``object_id`` (N,) uint16 mask ids, ``volume`` (N,) float32 m^3,
``stamps_ns`` (F,) int64 the frames' stamps, ``times`` (F,) float64 seconds since frame 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mosiv_ros.io.errors import BagError
from mosiv_ros.io.files import plain

GROUND_TRUTH_FILE = "ground_truth.yaml"
PARTICLES_FILE = "ground_truth_particles.npz"
FORMAT = "mosiv.ground_truth/1"


@dataclass
class GroundTruthParticles:
    """The simulated particles at every recorded frame (see the module docstring)."""

    positions: np.ndarray
    object_id: np.ndarray
    volume: np.ndarray
    stamps_ns: np.ndarray
    times: np.ndarray

    def of_object(self, object_id: int) -> np.ndarray:
        """Positions (F, N_k, 3) of the particles of object ``object_id``."""
        return self.positions[:, self.object_id == object_id]


def write_ground_truth(bag: str | Path, document: dict[str, Any], particles: GroundTruthParticles) -> None:
    """Write both sidecars into the existing bag directory ``bag``."""
    bag = Path(bag)
    text = yaml.safe_dump({"format": FORMAT, **plain(document), "particles_file": PARTICLES_FILE},
                          sort_keys=False)
    (bag / GROUND_TRUTH_FILE).write_text(text, encoding="utf-8")
    np.savez_compressed(
        bag / PARTICLES_FILE,
        positions=particles.positions.astype(np.float32),
        object_id=particles.object_id.astype(np.uint16),
        volume=particles.volume.astype(np.float32),
        stamps_ns=particles.stamps_ns.astype(np.int64),
        times=particles.times.astype(np.float64),
    )


def read_ground_truth(bag: str | Path) -> dict[str, Any]:
    """The ``ground_truth.yaml`` of a synthetic recording; BagError if it has none."""
    path = Path(bag) / GROUND_TRUTH_FILE
    try:
        document = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise BagError(bag, None, f"no readable {GROUND_TRUTH_FILE}: {exc.strerror}") from None
    if not isinstance(document, dict) or document.get("format") != FORMAT:
        raise BagError(bag, None, f"{GROUND_TRUTH_FILE} is not in the {FORMAT} format")
    return document


def read_ground_truth_particles(bag: str | Path) -> GroundTruthParticles:
    """The ``ground_truth_particles.npz`` of a synthetic recording; BagError if it has none."""
    path = Path(bag) / PARTICLES_FILE
    try:
        with np.load(path) as data:
            return GroundTruthParticles(**{key: data[key] for key in
                                           ("positions", "object_id", "volume", "stamps_ns", "times")})
    except (OSError, KeyError, ValueError) as exc:
        raise BagError(bag, None, f"unreadable {PARTICLES_FILE}: {exc}") from None


def ground_truth_if_any(bag: str | Path) -> tuple[dict[str, Any] | None, GroundTruthParticles | None]:
    """(ground_truth.yaml, its particles) of a synthetic recording; (None, None) for any other."""
    try:
        return read_ground_truth(bag), read_ground_truth_particles(bag)
    except BagError:
        return None, None
