"""Warp's runtime for the simulator: a quiet start, the device choice, kernels loaded safely.

Three things every simulation needs before its first launch, each done once per process:

- ``start()`` initialises Warp. On a machine without a usable CUDA driver, Warp's native library
  prints "Warp CUDA error" lines and a Python warning about the driver version while it looks
  for one; with the CPU as the answer that is not an error. Their text is kept at DEBUG level,
  and one INFO line says what was found.
- ``resolve_device(device)`` turns the one ``device`` setting ('auto', 'cpu', 'cuda:N') into
  a Warp device, with a clear error when CUDA is asked for and absent.
- ``load_modules(device, modules)`` compiles (on a cold kernel cache) and loads Warp modules
  before any launch, under a process-wide lock. Warp 1.4.2 builds a module lazily at its first
  launch without guarding the build against threads: the identifier's batched losses run one
  simulator per CPU core, and on an empty cache their first launches built the same module at
  once, which crashed (an LLVM "IO failure on output stream", or "Referencing undefined
  symbol" errors from the code generator). Loaded up front, a launch only looks its module up.
  Between processes (the nodes of a graph, the workers of a batch) a lock file in the kernel
  cache does the same: one builds a module, the others wait and then load it from the cache,
  instead of each building its own copy (Warp's per-process build directories made that safe,
  but on two cores a second build doubled the wait).

What it is not for: simulation itself (``simulator``) or choosing a torch device.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import sys
import tempfile
import threading
import time
import types
import warnings
from collections.abc import Iterable, Iterator

import warp as wp

from mosiv_ros.sim.errors import ParameterError

_LOG = logging.getLogger(__name__)
_LOCK = threading.RLock()
_started = False
_cuda_note = ""
"""Why no CUDA device is usable, from Warp's start-up output ('' when one is)."""
_noted: set[str] = set()
"""Devices whose choice has been logged."""
_loaded: set[tuple[str, str]] = set()
"""(device, module name) pairs loaded so far: the log says when kernels are compiled or loaded."""


@contextlib.contextmanager
def _captured_output() -> Iterator[io.StringIO]:
    """Collect what is printed to stdout and stderr, by Python and by native code alike."""
    text = io.StringIO()
    with tempfile.TemporaryFile(mode="w+b") as native:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        saved = [os.dup(fd) for fd in (1, 2)]
        try:
            for fd in (1, 2):
                os.dup2(native.fileno(), fd)
            with contextlib.redirect_stdout(text), contextlib.redirect_stderr(text), \
                    warnings.catch_warnings():
                warnings.simplefilter("ignore")
                yield text
        finally:
            for fd, copy in zip((1, 2), saved, strict=True):
                os.dup2(copy, fd)
                os.close(copy)
            native.seek(0)
            text.write(native.read().decode(errors="replace"))


def start() -> None:
    """Initialise Warp once, quietly (see the module docstring)."""
    global _started, _cuda_note
    with _LOCK:
        if _started:
            return
        wp.config.quiet = True  # no greeting, no per-module load lines: this module logs instead
        with _captured_output() as output:
            wp.init()
        _started = True
        said = [line.strip() for line in output.getvalue().splitlines() if line.strip()]
        for line in said:
            _LOG.debug("warp: %s", line)
        if wp.get_cuda_device_count() == 0:
            driver = wp.context.runtime.driver_version
            if not wp.context.runtime.is_cuda_enabled:
                _cuda_note = "this Warp build has no CUDA support"
            elif driver is None or driver == (0, 0):
                _cuda_note = "no CUDA driver found"
            else:
                _cuda_note = (f"CUDA driver {driver[0]}.{driver[1]} is older than Warp needs "
                              f"({'.'.join(map(str, wp.context.runtime.min_driver_version))})")


def resolve_device(device: str) -> str:
    """'auto' -> 'cuda:0' when a CUDA device is available, else 'cpu'; others checked, unchanged."""
    start()
    cuda = wp.get_cuda_device_count()
    if device == "auto":
        chosen = "cuda:0" if cuda > 0 else "cpu"
        _note_once(chosen)
        return chosen
    if device.startswith("cuda"):
        if cuda == 0:
            raise ParameterError(f"device {device!r} requested but no CUDA device is usable "
                                 f"({_cuda_note}); use 'cpu' or 'auto'")
        index = int(device.partition(":")[2] or 0)
        if index >= cuda:
            raise ParameterError(f"device {device!r} requested but only {cuda} CUDA device(s) exist")
    elif device != "cpu":
        raise ParameterError(f"unknown device {device!r}: expected 'auto', 'cpu' or 'cuda:N'")
    _note_once(device)
    return device


def _note_once(device: str) -> None:
    with _LOCK:
        if device in _noted:
            return
        _noted.add(device)
    if device == "cpu":
        _LOG.info("simulating on the CPU%s", f" ({_cuda_note})" if _cuda_note else "")
    else:
        _LOG.info("simulating on %s (%s)", device, wp.get_device(device).name)


@contextlib.contextmanager
def _cache_lock() -> Iterator[None]:
    """Hold the kernel cache's lock file.

    Where there is none to hold (not POSIX, a read-only cache, a file system without locks) only
    the process-wide lock holds, as Warp's per-process build directories keep a build safe.
    """
    with contextlib.ExitStack() as held:
        try:
            import fcntl

            os.makedirs(wp.config.kernel_cache_dir, exist_ok=True)
            handle = held.enter_context(open(os.path.join(wp.config.kernel_cache_dir, ".mosiv-build.lock"), "a"))
            fcntl.flock(handle, fcntl.LOCK_EX)
            held.callback(fcntl.flock, handle, fcntl.LOCK_UN)
        except (ImportError, OSError) as error:
            _LOG.debug("kernel cache not locked between processes: %s", error)
        yield


def load_modules(device: str, modules: Iterable[types.ModuleType | str]) -> None:
    """Compile if needed and load the Warp kernels of ``modules`` on ``device``, thread- and process-safely."""
    names = list(dict.fromkeys(m if isinstance(m, str) else m.__name__ for m in modules))
    with _LOCK:
        new = [name for name in names if (device, name) not in _loaded]
        if not new:
            return
        asked = time.perf_counter()
        with _cache_lock():
            began = time.perf_counter()
            if began - asked > 0.5:
                _LOG.info("waited %.1f s for another process building kernels into the cache",
                          began - asked)
            _LOG.info("loading the simulator's kernels on %s (compiled into the kernel cache %s "
                      "when not there yet)", device, wp.config.kernel_cache_dir)
            for name in new:
                module = wp.context.user_modules.get(name)
                if module is not None and module.kernels:  # a module of functions only is built into its users
                    if module.load(wp.get_device(device)) is None:
                        raise RuntimeError(f"Warp could not build the kernels of {name} on {device}")
                _loaded.add((device, name))
            _LOG.info("kernels ready on %s in %.1f s", device, time.perf_counter() - began)
