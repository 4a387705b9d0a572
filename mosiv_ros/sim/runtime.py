"""Warp's runtime for the simulator: a quiet start, the device choice, kernels built and loaded safely.

Three things every simulation needs before its first launch, each done once per process, and
a fourth that shortens the first run:

- ``start()`` initialises Warp. On a machine without a usable CUDA driver, Warp's native library
  prints "Warp CUDA error" lines and a Python warning about the driver version while it looks
  for one; with the CPU as the answer that is not an error. Their text is kept at DEBUG level,
  and one INFO line says what was found. Warp builds PTX for the device's own architecture
  (up to compute capability 9.0) rather than for 7.5.
- ``resolve_device(device)`` turns the one ``device`` setting ('auto', 'cpu', 'cuda:N') into
  a Warp device, with a clear error when CUDA is asked for and absent.
- ``load_modules(device, modules)`` compiles (on a cold kernel cache) and loads Warp modules
  before any launch, under a process-wide lock. Warp 1.4.2 builds a module lazily at its first
  launch without guarding the build against threads: the identifier's batched losses run one
  simulator per CPU core, and on an empty cache their first launches built the same module at
  once, which crashed (an LLVM "IO failure on output stream", or "Referencing undefined
  symbol" errors from the code generator). Loaded up front, a launch only looks its module up.
  Between processes (the nodes of a graph, the workers of a batch) a lock file per module in
  the kernel cache does the same: one builds a module, the others wait and then load it from
  the cache, instead of each building its own copy (Warp's per-process build directories made
  that safe, but on two cores a second build doubled the wait). A process takes first a module
  that no other is building: processes that start together build different modules at once.
- ``build_aside(device, names)`` starts helper processes (``build_free``) that build, beside
  this one, the modules of ``names`` that the kernel cache lacks. Alone, a process builds its
  modules one after another (an H200's machine took 10.8 s for the simulator's); with helpers
  the modules build side by side, and the build takes about as long as its largest module
  (7.8 s there).

What it is not for: simulation itself (``simulator``) or choosing a torch device.
"""

from __future__ import annotations

import atexit
import contextlib
import importlib
import io
import logging
import os
import subprocess
import sys
import tempfile
import threading
import time
import types
import warnings
from collections.abc import Iterable, Iterator, Sequence

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
        # where Warp builds PTX, for the device's own architecture up to compute capability 9.0
        # (Warp's default: 7.5 for every device), so that P2G has sm_90's vector reductions
        # (``warp_reduce.scatter``); the driver compiles it for the device as before
        wp.config.ptx_target_arch = max(wp.config.ptx_target_arch, 90)
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


def lock_file(name: str) -> str:
    """The lock file in the kernel cache that a build of module ``name`` holds."""
    return os.path.join(wp.config.kernel_cache_dir, f".mosiv-build.{name}.lock")


@contextlib.contextmanager
def _cache_lock(name: str, wait: bool = True) -> Iterator[bool]:
    """Hold the kernel cache's lock file of module ``name`` (``lock_file``); yield whether held.

    Without ``wait``, False (and nothing held) where another process holds it. Where there is no
    lock to hold (not POSIX, a read-only cache, a file system without locks) only the
    process-wide lock holds, as Warp's per-process build directories keep a build safe.
    """
    with contextlib.ExitStack() as held:
        free = True
        try:
            import fcntl

            os.makedirs(wp.config.kernel_cache_dir, exist_ok=True)
            handle = held.enter_context(open(lock_file(name), "a"))
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
                held.callback(fcntl.flock, handle, fcntl.LOCK_UN)
            except BlockingIOError:
                free = False
        except (ImportError, OSError) as error:
            _LOG.debug("kernel cache not locked between processes: %s", error)
        yield free


def cached(module: wp.context.Module, device: str) -> bool:
    """Whether the kernel cache holds ``module``, as its source is now, built for ``device``'s kind.

    Warp 1.4.2 (``Module.load``) keeps a module's build in ``wp_<name>_<the first seven hex
    digits of its hash>``: ``module_codegen.o`` for the CPU, ``module_codegen.sm<arch>.ptx`` or
    ``.cubin`` for CUDA. The hash is the one a load computes and keeps.
    """
    if module.hasher is None:
        module.hasher = wp.context.ModuleHasher(module)
    folder = os.path.join(wp.config.kernel_cache_dir, f"wp_{module.name}_{module.hasher.module_hash.hex()[:7]}")
    kind = (".o",) if device == "cpu" else (".ptx", ".cubin")
    try:
        return any(name.startswith("module_codegen") and name.endswith(kind) for name in os.listdir(folder))
    except OSError:  # not there (yet)
        return False


def _build(module: wp.context.Module, device: str) -> None:
    """Build (or load from the cache) and load ``module``'s kernels on ``device``."""
    built = not cached(module, device)
    if module.load(wp.get_device(device)) is None:
        raise RuntimeError(f"Warp could not build the kernels of {module.name} on {device}")
    _LOG.debug("kernels of %s ready on %s%s", module.name, device, " (built)" if built else "")


def _module(name: str) -> wp.context.Module:
    """Warp module ``name``: a Python module's, or one that the module it is named under makes (``kernels.p2g``'s)."""
    try:
        importlib.import_module(name)
    except ModuleNotFoundError:
        importlib.import_module(name.rpartition(".")[0])
    return wp.context.user_modules[name]


MAX_HELPERS = 3
"""The most helper processes ``build_aside`` starts. Each is a Python process with, on a GPU, a
CUDA context of its own, and a build takes at least as long as its largest module, which the
caller lists first: with six helpers on an H200 the six other modules were ready 2.9 s before
the largest (P2G with three threads a particle, 7.8 s)."""
_helpers: list[subprocess.Popen] = []
"""Helper processes (``build_aside``) of this process, ended at its exit if still building."""


def _end_helpers() -> None:
    for helper in _helpers:
        if helper.poll() is None:
            helper.kill()
            helper.wait()


def build_aside(device: str, names: Sequence[str]) -> list[subprocess.Popen]:
    """Start helper processes that build the modules of ``names`` the kernel cache lacks, beside this one.

    One fewer helper than those modules, no more than the cores less one, and at most
    ``MAX_HELPERS``: each takes a module that no process is building (``build_free``), and
    this process, loading them (``load_modules``), builds the others or waits for a helper's
    build and loads it from the cache. None where the cache holds every module. A helper still
    building when this process exits is ended with it.
    """
    start()
    modules = {name: _module(name) for name in names}  # imported outside the lock
    with _LOCK:  # a module's hash is computed once, as a load does it (``cached``)
        missing = [name for name, module in modules.items() if not cached(module, device)]
    count = min(len(missing) - 1, (os.cpu_count() or 1) - 1, MAX_HELPERS)
    if count <= 0:
        return []
    helpers = [start_helper(device, missing) for _ in range(count)]
    with _LOCK:
        if not _helpers:
            atexit.register(_end_helpers)
        _helpers.extend(helpers)
    _LOG.info("%d helper process(es) building kernels into the cache beside this one", count)
    return helpers


def start_helper(device: str, names: Sequence[str]) -> subprocess.Popen:
    """A helper process (``build_free``) for the modules ``names``, on this process's kernel cache."""
    command = [sys.executable, "-c", "import sys; from mosiv_ros.sim import runtime; "
               "runtime.build_free(sys.argv[1], sys.argv[2:])", device, *names]
    return subprocess.Popen(command, env=dict(os.environ, WARP_CACHE_PATH=wp.config.kernel_cache_dir),
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def build_free(device: str, names: Sequence[str]) -> None:
    """Build into the kernel cache each module of ``names`` that is not there and that no process is building.

    A helper's work (``build_aside``): the modules in order, each skipped where another process
    holds its lock (``_cache_lock``) or the cache holds it already.
    """
    start()
    device = resolve_device(device)
    for name in names:
        module = _module(name)
        with _cache_lock(name, wait=False) as free:
            if free and not cached(module, device):
                _build(module, device)


def load_modules(device: str, modules: Iterable[types.ModuleType | str]) -> None:
    """Compile if needed and load the Warp kernels of ``modules`` on ``device``, thread- and process-safely."""
    start()  # the kernel cache's directory is Warp's once it is initialised
    names = list(dict.fromkeys(m if isinstance(m, str) else m.__name__ for m in modules))
    with _LOCK:
        new = [name for name in names if (device, name) not in _loaded]
        if not new:
            return
        _LOG.info("loading the simulator's kernels on %s (compiled into the kernel cache %s "
                  "when not there yet)", device, wp.config.kernel_cache_dir)
        began, waited = time.perf_counter(), 0.0
        # a module of functions only is built into its users
        pending = [module for module in map(wp.context.user_modules.get, new) if module is not None and module.kernels]
        while pending:
            # first a module that no other process is building: processes that need the same
            # modules build different ones at once, then load the others' builds from the cache
            for module in pending:
                with _cache_lock(module.name, wait=False) as free:
                    if free:
                        _build(module, device)
                        break
            else:
                module = pending[0]
                asked = time.perf_counter()
                with _cache_lock(module.name):
                    waited += time.perf_counter() - asked
                    _build(module, device)
            pending.remove(module)
        _loaded.update((device, name) for name in new)
        if waited > 0.5:
            _LOG.info("waited %.1f s for another process building kernels into the cache", waited)
        _LOG.info("kernels ready on %s in %.1f s", device, time.perf_counter() - began)
