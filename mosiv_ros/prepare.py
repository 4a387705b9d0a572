"""A run's settings, and stages 1-2 of a recording in-process: ``RunConfig``, ``prepare``.

``prepare(bag, config)`` reads a recording, reconstructs every frame set (with its surface
tracks) and lifts the first complete one (``Prepared``), as reconstruction_node and lifting_node
do on topics; ``RunConfig``
holds every stage's settings (the node parameters) and the held-out part of the recording.

What it is for: everything that starts from a recording in-process, kept below the loop
closure (``loop``) and the whole pipeline (``pipeline``: the fit, the twin, the scores and
the report), which both build on it. What it is not for: the stages' algorithms (``recon``,
``lifting``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

from mosiv_ros.config import HOLDOUT, IdentifyConfig, LiftingConfig, PredictionConfig, ReconstructionConfig
from mosiv_ros.io.bag import read_recording
from mosiv_ros.io.errors import BagError
from mosiv_ros.io.recording import Recording
from mosiv_ros.lifting.lift import LiftedParticles, lift_first_complete
from mosiv_ros.progress import Progress
from mosiv_ros.recon.reconstruct import ObservedFrame, iter_reconstruct
from mosiv_ros.recon.tracks import SurfaceTracks

_LOG = logging.getLogger(__name__)


@dataclass
class RunConfig:
    """Every stage's settings (the node parameters) plus the held-out part of the recording."""

    reconstruction: ReconstructionConfig = field(default_factory=ReconstructionConfig)
    lifting: LiftingConfig = field(default_factory=LiftingConfig)
    identify: IdentifyConfig = field(default_factory=IdentifyConfig)
    prediction: PredictionConfig = field(default_factory=PredictionConfig)
    holdout: float = HOLDOUT
    """Fraction of the recording's frames kept out of the fit, to score predictions on."""
    render: bool = True
    """Score 2D metrics (IoU, PSNR, SSIM) by re-rendering the twin."""


@dataclass
class Prepared:
    """Stages 1-2 of a recording.

    The recording, its observed frames from the lifted one on, the lifted particles, the time
    they took, and the surface tracks over those frames (``tracks.from_frame(0)``: the tracks a
    loss can attach to the particles).
    """

    bag: Path
    recording: Recording
    frames: list[ObservedFrame]
    lifted: LiftedParticles
    timing: dict[str, float]
    tracks: SurfaceTracks


def prepare(bag: str | Path, config: RunConfig,
            progress: Progress | None = None) -> Prepared:
    """Reconstruct every frame set and lift the first complete one."""
    timing: dict[str, float] = {}
    tick = time.perf_counter()
    recording = read_recording(bag)
    frames = []
    n_sets = min(len(c.frames) for c in recording.cameras.values())
    _LOG.info("stage 1, reconstruction: %d frame sets", n_sets)
    for frame in iter_reconstruct(recording, config.reconstruction, recording.scene):
        frames.append(frame)
        if progress:
            progress("reconstruct", len(frames), n_sets, "frame")
    timing["reconstruct_s"] = time.perf_counter() - tick
    if len(frames) < 3:
        raise BagError(bag, None, f"only {len(frames)} frame sets: need at least 3 to fit and test")
    _LOG.info("stage 2, lifting")
    tick = time.perf_counter()
    lifted = lift_first_complete(frames, config.lifting, recording.scene)
    timing["lift_s"] = time.perf_counter() - tick
    _LOG.info("lifted: %s", lifted.summary())
    frames = [f for f in frames if f.stamp_ns >= lifted.stamp_ns]
    return Prepared(Path(bag), recording, frames, lifted, timing, SurfaceTracks.of([f.tracks for f in frames]))
