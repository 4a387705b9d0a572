"""Files the pipeline writes: whole or not at all, in a place checked before the work starts.

What it is for:

- ``replacing(path)``: every output (estimates, reports, plots, checkpoints, identify_node's
  YAML) is written to a temporary file in the same directory and renamed over ``path`` once it
  is complete, so an interrupted write (an exception, a killed process) leaves the previous
  file as it was, never a partial one;
- ``OutputDir``: a run's output directory, checked when it is opened (a directory, created if
  missing, that a file can be written into), before any work. Its files are one run's only:
  the first file a run writes there removes the files an older run wrote (listed in
  ``MANIFEST``, which also names the run), so a directory holds either the older run's complete
  set or the newer run's, never a mix. Files the pipeline did not write are left alone;
- ``check_new_path(path)``: the same check for an output that must not exist yet (a bag, a
  suite), made before minutes of simulation rather than after; ``check_output_file(path)`` for
  one file (identify_node's ``output_yaml``, checked when the node starts);
- ``plain(value)``: a report's or a sidecar's dictionary with numpy values made plain Python.

What it is not for: writing bags (``io.bag``, with rosbags).
"""

from __future__ import annotations

import datetime
import math
import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mosiv_ros.io.errors import OutputError
from mosiv_ros.io.scene import load_yaml

MANIFEST = "outputs.yaml"
"""The file of an output directory naming the run that wrote it and the files it wrote."""
FIGURE_DPI = 90
"""Resolution of the reports' plots."""


@contextmanager
def replacing(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; renamed onto ``path`` if the block succeeds.

    The temporary name keeps ``path``'s suffix (``np.savez`` and ``savefig`` go by it). When the
    block raises, the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through ``replacing``; return the path."""
    path = Path(path)
    with replacing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def _check_directory(path: Path) -> None:
    """OutputError unless ``path`` is (or can be made) a directory a file can be written into."""
    if path.exists() and not path.is_dir():
        raise OutputError(path, "is a file, not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(path, f"cannot create the directory: {exc.strerror}") from None
    probe = path / f".mosiv-probe-{uuid.uuid4().hex[:12]}"
    try:  # os.access is not enough: it says yes to root on a read-only mount or in /sys
        probe.touch(exist_ok=False)
    except OSError as exc:
        raise OutputError(path, f"cannot write into the directory: {exc.strerror}") from None
    probe.unlink()


def check_new_path(path: str | Path) -> Path:
    """OutputError unless ``path`` does not exist and its directory can take it; return it."""
    path = Path(path)
    if path.exists():
        raise OutputError(path, "already exists (the output must be a new path)")
    _check_directory(path.absolute().parent)
    return path


def check_output_file(path: str | Path) -> Path:
    """OutputError unless a file can be written at ``path`` (its directory is created if missing)."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(path, "is a directory, not a file")
    _check_directory(path.absolute().parent)
    return path


class OutputDir:
    """A run's output directory (see the module docstring); opening it checks the location.

    ``run`` describes the run (e.g. the command and its bag); it goes into the manifest.
    """

    def __init__(self, path: str | Path, run: str) -> None:
        self.path = Path(path)
        _check_directory(self.path)
        self.run = run
        self.started = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        self.files: list[str] = []

    @contextmanager
    def replacing(self, name: str) -> Iterator[Path]:
        """``replacing`` the file ``name`` of this directory, as one of this run's outputs."""
        with replacing(self.path / name) as tmp:
            yield tmp
            self._own(name)  # the file is complete: now the older run's files may go

    def write_text(self, name: str, text: str) -> Path:
        """Write one of this run's files whole; return its path."""
        with self.replacing(name) as tmp:
            tmp.write_text(text, encoding="utf-8")
        return self.path / name

    def save_figure(self, name: str, figure: Any) -> Path:
        """Save a matplotlib ``figure`` as one of this run's files (by ``name``'s suffix), whole."""
        with self.replacing(name) as tmp:
            figure.savefig(tmp, dpi=FIGURE_DPI)
        return self.path / name

    def claim(self, name: str) -> Path:
        """Count ``name`` as this run's file, to be written by another process (identify_node).

        The older run's files go now, ``name`` among them.
        """
        self._own(name)
        (self.path / name).unlink(missing_ok=True)
        return self.path / name

    def _own(self, name: str) -> None:
        if not self.files:  # this run's first file: the older run's files go
            for old in self._older_files():
                if old != name:  # replaced in one step by the caller
                    (self.path / old).unlink(missing_ok=True)
        if name not in self.files:
            self.files.append(name)
            write_text(self.path / MANIFEST, yaml.safe_dump(
                {"run": self.run, "started": self.started, "files": self.files}, sort_keys=False))

    def _older_files(self) -> list[str]:
        """The files an older run listed in the manifest (plain names inside this directory)."""
        try:
            document = load_yaml((self.path / MANIFEST).read_text(encoding="utf-8"))
            files = document["files"]
        except (OSError, UnicodeDecodeError, yaml.YAMLError, KeyError, TypeError):
            return []
        if not isinstance(files, list):
            return []
        return [name for name in files if isinstance(name, str) and name == Path(name).name
                and name not in (MANIFEST, "", ".", "..")]


def plain(value: Any, null_nonfinite: bool = False) -> Any:
    """``value`` with numpy arrays, numpy scalars and paths made plain Python, for YAML or JSON.

    Nested in dicts, lists and tuples too. With ``null_nonfinite`` (JSON has no inf or NaN),
    non-finite floats become None (null).
    """
    if isinstance(value, dict):
        return {str(k): plain(v, null_nonfinite) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v, null_nonfinite) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist(), null_nonfinite)
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, Path):
        return str(value)
    if null_nonfinite and isinstance(value, float) and not math.isfinite(value):
        return None
    return value
