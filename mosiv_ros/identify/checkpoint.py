"""A fit's checkpoint: the state after an iteration, written so that a rerun of the same fit resumes.

``Checkpoint(directory, signature)``: ``save(state)`` writes a ``curriculum.FitState`` to
``directory/CHECKPOINT_FILE`` (whole or not at all, ``io.files.replacing``), ``load()`` reads it
back, or returns None where there is none, where it belongs to another fit (another
``signature``) or where it cannot be read (a partial or corrupt file: logged, the fit starts
afresh). Before the first state, ``save_search(rounds)`` keeps the search's finished rounds in
``SEARCH_FILE`` (``search.GlobalSearch.run`` says what a round holds) and ``load_search()`` reads
them back on the same terms; ``save`` removes that file, which its state replaces.
``signature(...)`` names a fit: its problem and the settings its result depends on.

What it is for: resuming a fit. What it is not for: the fit's results (``identify.estimates``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import zipfile
from pathlib import Path

import numpy as np

from mosiv_ros.identify.curriculum import Adam, FitState
from mosiv_ros.io.files import replacing, write_text

_LOG = logging.getLogger(__name__)

CHECKPOINT_FILE = "identify_checkpoint.npz"
SEARCH_FILE = "search_checkpoint.json"


def signature(problem, labels: list[str], settings: dict) -> str:
    """The hash that names a fit.

    Of ``problem`` (a ``fit.FitProblem``), its free entries' ``labels`` and the ``settings`` its
    result depends on (``FitSettings.result_settings``).
    """
    obs = problem.observations
    text = json.dumps({
        "objects": [(o.name, o.family) for o in problem.objects],
        "free": labels, "frames": obs.n_frames,
        "frame_dt": obs.frame_dt, "particles": int(len(problem.particles.object_index)),
        "centroids": np.round(np.nan_to_num(obs.centroids()), 6).tolist(),
        "tracks": 0 if obs.tracks is None else obs.tracks.n_tracks,
        "settings": settings,
        "initial_velocity": _rounded(problem.initial_velocity),
        "warm_start": [_rounded(a) for a in problem.warm_start or ()],
    })
    return hashlib.sha256(text.encode()).hexdigest()


def _rounded(a: np.ndarray | None) -> list | None:
    return None if a is None else np.round(np.nan_to_num(np.asarray(a, dtype=np.float64)), 9).tolist()


class Checkpoint:
    """The checkpoint of the fit named ``signature`` in ``directory`` (empty: none kept)."""

    def __init__(self, directory: str, signature: str) -> None:
        self.directory = directory
        self.signature = signature

    @property
    def path(self) -> Path:
        return Path(self.directory) / CHECKPOINT_FILE

    def save(self, state: FitState) -> None:
        """Write ``state`` over the previous checkpoint (nothing without a directory)."""
        if not self.directory:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        adam, best = state.adam, state.best
        with replacing(self.path) as tmp:
            np.savez(tmp, signature=self.signature, u=state.u, velocity=state.velocity,
                     start_u=state.start[0], start_velocity=state.start[1], best_loss=best[0],
                     best_u=best[1], best_velocity=best[2], best_per=best[3], m=adam.m, v=adam.v,
                     t=adam.t, lr=adam.lr, stage=state.stage, iteration=state.iteration,
                     failures=state.failures, history=json.dumps(state.history))
        (Path(self.directory) / SEARCH_FILE).unlink(missing_ok=True)  # the state holds the search's end

    def save_search(self, rounds: list[dict]) -> None:
        """Write the search's finished ``rounds`` (JSON values) over the previous ones (none without a directory)."""
        if not self.directory:
            return
        Path(self.directory).mkdir(parents=True, exist_ok=True)
        write_text(Path(self.directory) / SEARCH_FILE,
                   json.dumps({"signature": self.signature, "rounds": rounds}))

    def load_search(self) -> list[dict]:
        """The finished rounds of this fit's search, or [] (see the module docstring)."""
        path = Path(self.directory) / SEARCH_FILE
        if not self.directory or not path.is_file():
            return []
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            if data["signature"] != self.signature:
                _LOG.warning("%s belongs to another problem or settings; searching afresh", path)
                return []
            return list(data["rounds"])
        except (OSError, KeyError, TypeError, ValueError) as error:  # partial or corrupt
            _LOG.warning("cannot read the search's checkpoint %s (%s: %s); searching afresh", path,
                         type(error).__name__, error)
            return []

    def load(self) -> FitState | None:
        """The saved state of this fit, or None (see the module docstring)."""
        if not self.directory or not self.path.is_file():
            return None
        path = self.path
        try:
            data = np.load(path)
            if str(data["signature"]) != self.signature:
                _LOG.warning("%s belongs to another problem or settings; starting afresh", path)
                return None
            adam = Adam(data["lr"])
            adam.m, adam.v, adam.t = data["m"], data["v"], int(data["t"])
            return FitState(data["u"], data["velocity"], adam, (data["start_u"], data["start_velocity"]),
                            (float(data["best_loss"]), data["best_u"], data["best_velocity"],
                             data["best_per"]),
                            json.loads(str(data["history"])), int(data["stage"]),
                            int(data["iteration"]), int(data["failures"]))
        except (OSError, EOFError, KeyError, ValueError, zipfile.BadZipFile) as error:  # partial or corrupt
            _LOG.warning("cannot read checkpoint %s (%s: %s); starting afresh", path,
                         type(error).__name__, error)
            return None
