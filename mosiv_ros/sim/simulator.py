"""The differentiable multi-object MLS-MPM simulator: set-up, rollouts, gradients.

A ``Simulator`` holds one scene (objects, their particles, boundaries, effects) and B parameter
sets of it (a leading batch axis: every kernel runs all B at once). ``rollout`` advances whole
frames and returns particle positions per frame; with ``grad=True`` it keeps one checkpoint of the
particle state per frame, and ``backward`` then takes dL/dx at every frame and returns dL/d(every
parameter), dL/d(initial velocities) and dL/d(particle volumes). The backward pass recomputes
one frame's substeps at a time on a ``wp.Tape`` from that frame's checkpoint, so memory grows
with the number of frames, not substeps. On a CUDA device, where the frames' substep states and
grids fit in ``SimConfig.tape_memory``, the rollout records each frame on the tape's buffers and
keeps a copy of them, and the backward puts each back (one copy) instead of recomputing it.

On a CUDA device a frame's substeps are hundreds of small kernel launches, and at the particle
counts of an identification (thousands) launching them from Python costs more than running
them. So a frame's substeps (forward) and their adjoints (backward) run as CUDA graphs of runs
of substeps that frames of every substep count share (``graph_runs``), each captured on its
first run (after its kind's first, which loads the kernels) and replayed from then on; the
arrays a graph touches live as long as the simulator (``SimConfig.cuda_graphs`` turns this off).

Time step: ``n`` equal substeps per frame, the fewest that keep dt below the CFL bound
``cfl * dx / (c + max_speed)`` (c the largest elastic or acoustic wave speed over objects and
batches) and every effect's own bound. A frame whose particles turn non-finite, move faster
than one grid cell per substep, invert, or leave the domain stops the run with a
``SimulationDiverged`` naming the object, parameter set and frame.

What it is not for: losses, optimisation or observations (``mosiv_ros.identify``).
"""

from __future__ import annotations

import gc
import logging
import math
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
import warp as wp

from mosiv_ros.sim import kernels
from mosiv_ros.sim.boundaries import COLLIDER_SHAPES, GROUND_PARAMS, WALL_CELLS, Collider, Ground
from mosiv_ros.sim.effects import Effect, Gravity, GridView, ParticleView
from mosiv_ros.sim.errors import ParameterError, SimulationDiverged
from mosiv_ros.sim.materials import FAMILY_CODES, MATERIAL_PARAMS, wave_speed
from mosiv_ros.sim.params import REPLICAS, Parameters, lane_count
from mosiv_ros.sim.runtime import load_modules, resolve_device

_LOG = logging.getLogger(__name__)


@dataclass
class ObjectModel:
    """One simulated object: name, material family and initial parameter values (SI units)."""

    name: str
    family: str
    params: dict[str, float] = field(default_factory=dict)
    id: int = 0


@dataclass
class Particles:
    """Initial particles of a scene.

    Positions (N, 3) m, volumes (N,) m^3, object index (N,) into the simulator's object list,
    and optional initial velocities (N, 3) m/s (default zero).
    """

    x: np.ndarray
    volume: np.ndarray
    object_index: np.ndarray
    v: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.x = np.asarray(self.x, dtype=np.float64).reshape(-1, 3)
        n = len(self.x)
        self.volume = np.broadcast_to(np.asarray(self.volume, dtype=np.float64), (n,)).copy()
        self.object_index = np.asarray(self.object_index, dtype=np.int32).ravel()
        self.v = (np.zeros((n, 3)) if self.v is None
                  else np.asarray(self.v, dtype=np.float64).reshape(n, 3))
        if len(self.object_index) != n:
            raise ValueError(f"object_index has {len(self.object_index)} entries for {n} particles")
        if not np.all(np.isfinite(self.x)) or not np.all(np.isfinite(self.v)):
            raise ValueError("particle positions and velocities must be finite")
        if np.any(self.volume <= 0):
            raise ValueError("particle volumes must be positive")


@dataclass
class SimConfig:
    """Grid, time stepping, boundaries and effects of a simulation.

    The grid covers the box ``lo``..``hi`` (metres, world frame) with spacing ``dx``; particles
    must start at least ``WALL_CELLS + 1`` cells inside it. ``max_speed`` is the material speed
    (m/s) the CFL bound allows for on top of the wave speed. ``cuda_graphs``: on a CUDA device,
    replay a frame's substeps (and their adjoints) as captured CUDA graphs of runs of substeps
    (``graph_runs``); off, every kernel is launched from Python (same results up to the order of
    float atomics).
    ``cell_order``: keep the particles sorted by grid cell inside the simulator (callers see
    their own order). None (default): on a CUDA device, sort unless the given order already
    runs along lines of cells a warp long (``cell_lines`` at least ``SORT_LINES``); on the CPU,
    never (``Simulator._stencil_cells`` says why). ``tape_memory``: GB that a
    ``grad=True`` rollout on a CUDA device may keep every frame's substep states and grids in,
    so that ``backward`` copies each frame's back and runs its adjoint instead of first
    recomputing it; a rollout that needs more, every rollout at 0, and every rollout on the CPU
    (where a second thread recomputes a frame while the adjoint of the next one runs) keep one
    checkpoint a frame and recompute. None (default): a third of the device's memory, at most half
    of what is free (a card shared with other processes).
    """

    dx: float
    lo: Sequence[float]
    hi: Sequence[float]
    frame_dt: float = 1.0 / 30.0
    cfl: float = 0.4
    max_speed: float = 5.0
    max_substeps: int = 10000
    ground: Ground | None = field(default_factory=Ground)
    colliders: list[Collider] = field(default_factory=list)
    effects: list[Effect] = field(default_factory=lambda: [Gravity()])
    device: str = "auto"
    cuda_graphs: bool = True
    cell_order: bool | None = None
    tape_memory: float | None = None


def domain_around(points: np.ndarray, dx: float, margin: float = 0.1,
                  floor: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A box around ``points`` with ``margin`` metres on every side plus the wall cells.

    With ``floor`` (a ground height), the box reaches below it by the wall cells too. The box
    snaps outwards to multiples of ``dx``, so that every domain of one ``dx`` puts its grid nodes
    at the same world positions: MPM is not translation invariant at the scale of a cell, and two
    simulations of one scene on grids offset by part of a cell (the synthetic recorder's and the
    identifier's) drifted 2 cm apart in a second of contact.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pad = margin + (WALL_CELLS + 1) * dx
    lo, hi = points.min(axis=0) - pad, points.max(axis=0) + pad
    if floor is not None:
        lo[2] = min(lo[2], floor - (WALL_CELLS + 1) * dx)
    return np.floor(lo / dx - 1e-9) * dx, np.ceil(hi / dx + 1e-9) * dx


WALL_RETRIES = 3
"""How many times a rollout whose objects reached the domain's walls is widened and run again."""


def reaches_walls(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, dx: float) -> bool:
    """Whether any position of ``x`` (..., 3) came within the wall cells of the domain lo..hi.

    There the domain's walls, which are not part of any scene, would have stopped it: a rollout
    that reaches them must be run again on a wider domain (``domain_around`` what it visited).
    """
    inner = (WALL_CELLS + 1) * dx
    x = np.asarray(x).reshape(-1, 3)
    return bool(np.any(x.min(axis=0) < np.asarray(lo) + inner) or np.any(x.max(axis=0) > np.asarray(hi) - inner))


@dataclass
class SimState:
    """Particle state of every batch.

    x, v (B, N, 3); C (affine velocity field) and b (elastic left Cauchy-Green tensor)
    (B, N, 3, 3). ``SimState.rest(x, v)`` starts undeformed.
    """

    x: np.ndarray
    v: np.ndarray
    C: np.ndarray
    b: np.ndarray

    @classmethod
    def rest(cls, x: np.ndarray, v: np.ndarray) -> SimState:
        x = np.asarray(x, dtype=np.float64)
        zero = np.zeros(x.shape[:-1] + (3, 3))
        return cls(x=x, v=np.broadcast_to(v, x.shape).copy(), C=zero,
                   b=zero + np.eye(3))


@dataclass
class Gradients:
    """dL/d(...) from ``Simulator.backward``.

    Per parameter name (shaped like the parameter), initial velocities (B, N, 3) and particle
    volumes (B, N).
    """

    params: dict[str, np.ndarray]
    v0: np.ndarray
    volume: np.ndarray


@dataclass
class QueuedRollout:
    """A rollout queued on the simulator's device and not yet waited for (``Simulator.queue_rollout``).

    ``positions``: ((F + 1) B N,) ``wp.vec3`` on the simulator's device, frame-major, then row,
    then particle, in the callers' order: what ``rollout`` returns, there. Work queued after the
    rollout on the simulator's stream, or on a stream made to wait for it, reads the values.
    ``wait()`` waits for the rollout, raises ``SimulationDiverged`` where ``rollout`` would, and
    makes it the simulator's last rollout (for ``backward`` and ``last_state``); it must come
    before the simulator's next rollout.
    """

    positions: wp.array
    wait: Callable[[], None]


SORT_LINES = 32
"""``SimConfig.cell_order``'s default keeps the given order where its lines of cells
(``cell_lines``) are at least this many particles long, a CUDA warp's lanes: a warp then
scatters along one line. A lattice with shorter lines, and particles in any looser order,
are sorted (benchmarks/RESULTS.md, "Particles sorted by cell where their lines are short")."""


def cell_lines(cells: np.ndarray) -> float:
    """The mean length, in particles, of the runs of consecutive particles along one line of cells.

    ``cells`` are the linear indices of the particles' stencil cells (``Simulator._stencil_cells``,
    the last axis fastest): a run goes on while each particle's cell is its predecessor's or the
    next one along that axis. A lattice ordered as ``sim.sampling`` makes it (two particles to a
    cell along the fastest axis) runs as long as the object is along that axis; random order
    about one particle.
    """
    steps = np.diff(cells)
    return len(cells) / (1 + np.count_nonzero((steps != 0) & (steps != 1)))


class _Arena:
    """Zero-initialised arrays that share one allocation, so that one memset clears them all.

    A substep's grid is ten arrays and a frame's backward clears the gradients of some thousand
    (four per state and nine per grid, for each of its substeps): on a GPU each clear is a
    memset node of about a microsecond whatever its size, which at the few thousand particles
    of an identification was a fifth of a frame's backward (benchmarks/RESULTS.md). The arrays
    are views of ``memory``, which only the arena holds: whoever keeps the arrays keeps it.
    ``memory`` may be given: an array of a larger arena, which holds several arenas.

    Raw memory is counted in ``WORD``s of ``ALIGN`` bytes: a frame's tape at a million particles
    is some 10 GB, more float32 elements than a Warp array's 32-bit shape can count.
    """

    ALIGN = 16
    WORD = wp.vec4  # ALIGN bytes

    def __init__(self, specs: list[tuple[int, type]], device: str, memory: wp.array | None = None) -> None:
        offsets = self.offsets(specs)
        total = offsets.pop()
        self.memory = memory if memory is not None else wp.zeros(max(total, self.ALIGN) // self.ALIGN,
                                                                 dtype=self.WORD, device=device)
        self.arrays = [wp.array(ptr=self.memory.ptr + offset, dtype=dtype, shape=(n,),
                                device=device, owner=False)
                       for offset, (n, dtype) in zip(offsets, specs, strict=True)]

    @classmethod
    def offsets(cls, specs: list[tuple[int, type]]) -> list[int]:
        """Where each array of ``specs`` starts in the arena, and (last) the arena's bytes."""
        offsets = [0]
        for n, dtype in specs:
            offsets.append(offsets[-1] + -(-n * wp.types.type_size_in_bytes(dtype) // cls.ALIGN) * cls.ALIGN)
        return offsets

    @classmethod
    def raw(cls, nbytes: int) -> tuple[int, type]:
        """The spec of ``nbytes`` (a multiple of ``ALIGN``) of raw memory: that many bytes in ``WORD``s."""
        return nbytes // cls.ALIGN, cls.WORD

    def zero(self) -> None:
        self.memory.zero_()


class _Staging:
    """Copies from a CUDA device to the host through page-locked host memory kept for the next.

    On an H100 host a copy from the device into new pageable memory ran at 1.2-1.5 GB/s (a
    million particles' four-frame trajectory, 60 MB, in 40-51 ms), into page-locked memory at 50
    GB/s (1.2 ms). The host then copies the staged values into the caller's new array (12-15 ms
    for the 60 MB there): a download in parts (``stage``, ``part`` as each is computed,
    ``collect``) does that part by part while the device computes the next. The buffer grows to
    the largest download and is reused once ``collect`` has waited for every part. Uploads
    (``reserve``, ``put``) go through it too. On the CPU the arrays are read and written
    directly.
    """

    # Smaller parts grow until they are this large: waiting for each part keeps the host at most
    # a part ahead of the device, and a sample bag's fit (36 KB of positions a frame) ran its
    # window's forward up to 5 % slower with a copy and a wait per frame.
    OVERLAP_BYTES = 1 << 22

    def __init__(self, device: str) -> None:
        self._cuda = device.startswith("cuda")
        self._device = device
        self._buffer: wp.array | None = None
        self._events: list[wp.Event] = []
        self._source: wp.array | None = None
        self._dtype: type | None = None
        self._staged: wp.array | None = None
        self._parts: list[tuple[int, int]] = []  # (start, end) of each part queued so far
        self._done = 0  # the parts in ``_out``
        self._out: np.ndarray | None = None

    def _host(self, dtype: type, n: int) -> wp.array:
        """A host array of ``n`` elements of ``dtype`` on the page-locked buffer."""
        nbytes = n * wp.types.type_size_in_bytes(dtype)
        if self._buffer is None or self._buffer.capacity < nbytes:
            if self._buffer is not None:  # no copy in flight may touch the old buffer once freed
                wp.synchronize_stream(wp.get_stream(self._device))
            self._buffer = None  # free the old buffer first
            self._buffer = wp.empty(-(-nbytes // _Arena.ALIGN), dtype=_Arena.WORD, device="cpu", pinned=True)
        return wp.array(ptr=self._buffer.ptr, dtype=dtype, shape=(n,), device="cpu", owner=False)

    def stage(self, array: wp.array, dtype: type | None = None) -> None:
        """Start a download of the one-dimensional ``array``, whose parts the device computes in order.

        ``dtype``: the host array's numpy type (converted as copied), by default the array's own.
        """
        self._source, self._dtype, self._parts, self._done = array, dtype, [], 0
        if self._cuda:
            self._staged = self._host(array.dtype, array.shape[0])
            self._out = np.empty_like(self._staged.numpy(), dtype=dtype)

    def part(self, end: int) -> None:
        """Queue the copy of the elements from the last part's end to ``end``, if they are ``OVERLAP_BYTES`` or more.

        The copy follows the device's work so far; the part before is then copied into the new
        host array while the device works on.
        """
        if not self._cuda or (end - self._end()) * wp.types.type_size_in_bytes(
                self._source.dtype) < self.OVERLAP_BYTES:
            return  # a later part, or ``collect``, takes these elements with it
        self._queue(end)
        if len(self._parts) > 1:
            self._take(len(self._parts) - 1)

    def _end(self) -> int:
        """Where the parts queued so far end."""
        return self._parts[-1][1] if self._parts else 0

    def _queue(self, end: int) -> None:
        start = self._end()
        if end == start:
            return
        if len(self._events) == len(self._parts):
            self._events.append(wp.Event(self._device))
        wp.copy(self._staged, self._source, dest_offset=start, src_offset=start, count=end - start)
        wp.get_stream(self._device).record_event(self._events[len(self._parts)])
        self._parts.append((start, end))

    def _take(self, parts: int) -> None:
        """Copy the staged parts before ``parts`` that are not yet in the host array, once copied to the host."""
        staged = self._staged.numpy()
        for index in range(self._done, parts):
            start, end = self._parts[index]
            wp.synchronize_event(self._events[index])
            self._out[start:end] = staged[start:end]
        self._done = max(self._done, parts)

    def collect(self) -> np.ndarray:
        """The staged array's values in a new host array (the rest queued as a last part)."""
        if not self._cuda:
            source, self._source = self._source, None
            return np.array(source.numpy(), dtype=self._dtype)  # a copy, not a view of the simulator's memory
        self._queue(self._source.shape[0])
        self._source = None
        self._take(len(self._parts))
        out, self._out = self._out, None
        return out

    def download(self, array: wp.array, dtype: type | None = None) -> np.ndarray:
        """A new host array of the one-dimensional ``array``'s values (``dtype`` as ``stage``), once computed."""
        self.stage(array, dtype)
        return self.collect()

    def reserve(self, dtype: type, n: int) -> None:
        """Room for ``put`` to stage ``n`` elements of ``dtype``, once every copy through the buffer is done."""
        if self._cuda:
            wp.synchronize_stream(wp.get_stream(self._device))
            self._host(dtype, n)

    def put(self, values: np.ndarray, dtype: type, dest: wp.array, offset: int) -> None:
        """Copy ``values`` (float32, a row an element of ``dtype``) into ``dest`` after the device's work so far.

        Staged at element ``offset`` of the room ``reserve`` made: puts at different offsets
        may be in flight together, and the host goes on at once.
        """
        if not self._cuda:
            dest.assign(np.ascontiguousarray(values))
            return
        size = wp.types.type_size_in_bytes(dtype)
        staged = wp.array(ptr=self._buffer.ptr + offset * size, dtype=dtype, shape=(len(values),), device="cpu",
                          owner=False)
        staged.numpy()[...] = values
        wp.copy(dest, staged)


Memory = tuple[wp.array, wp.array | None]
"""Where an arena's values and gradients go (arrays of larger arenas), or None for allocations of their own."""


def _arrays(specs: list[tuple[int, type]], device: str, requires_grad: bool,
            memory: Memory | None = None) -> tuple[list[wp.array], _Arena, _Arena | None]:
    """Arrays of ``specs`` in one arena, their gradients (if asked) in another."""
    values = _Arena(specs, device, memory[0] if memory else None)
    grads = _Arena(specs, device, memory[1] if memory else None) if requires_grad else None
    if grads is not None:
        for array, grad in zip(values.arrays, grads.arrays, strict=True):
            array.grad = grad
    return values.arrays, values, grads


def _momentum_and_mass(nodes: wp.array, interleaved: bool) -> tuple[wp.array, wp.array]:
    """The momenta (``wp.vec3``) and masses (float) of a grid, as views of ``nodes`` (``wp.vec4``, 16 bytes a node).

    ``interleaved``: a node's momentum and mass share its aligned 16-byte slot, momentum first
    (strided views), so that P2G adds the four with one vector reduction (``warp_reduce.scatter``;
    on an H200 P2G took a quarter to a half less time). Otherwise every momentum comes first,
    then every mass: built without the vector reduction (for compute capability 7.5, on the same
    H200) P2G was slower interleaved, its two atomic adds hitting one slot. ``vector_reductions``
    picks.
    """
    n, device = nodes.shape[0], nodes.device
    vec3 = wp.types.type_size_in_bytes(wp.vec3)
    if interleaved:
        stride = wp.types.type_size_in_bytes(wp.vec4)
        return (_slot_vectors(nodes),
                wp.array(ptr=nodes.ptr + vec3, dtype=float, shape=(n,), strides=(stride,), device=device, owner=False))
    return (wp.array(ptr=nodes.ptr, dtype=wp.vec3, shape=(n,), device=device, owner=False),
            wp.array(ptr=nodes.ptr + n * vec3, dtype=float, shape=(n,), device=device, owner=False))


def _slot_vectors(slots: wp.array) -> wp.array:
    """The first three floats of each 16-byte slot of ``slots`` (``wp.vec4``), as a strided ``wp.vec3`` view."""
    stride = wp.types.type_size_in_bytes(wp.vec4)
    return wp.array(ptr=slots.ptr, dtype=wp.vec3, shape=slots.shape, strides=(stride,), device=slots.device,
                    owner=False)


def vector_reductions(device: str) -> bool:
    """Whether ``device`` adds four floats in one reduction (CUDA, compute capability 9.0 or later).

    Warp builds the kernels for it (``runtime.start``), and the grids interleave momenta and
    masses there (``_momentum_and_mass``).
    """
    return device.startswith("cuda") and wp.get_device(device).arch >= 90


class _State:
    """Particle state arrays of all batches: x, v, C (affine field), b (elastic F F^T).

    A kernel reads them as ``<role>_x``, ... where the launch passes the state as ``<role>``
    (``src``, ``dst``, ``state``; see ``_bind``). The gradients share one allocation
    (``_Arena``): ``zero_grad`` clears them at once.
    """

    def __init__(self, n: int, device: str, requires_grad: bool, memory: Memory | None = None) -> None:
        (self.x, self.v, self.C, self.b), self._values, self._grads = _arrays(
            self.specs(n), device, requires_grad, memory)

    @staticmethod
    def specs(n: int) -> list[tuple[int, type]]:
        return [(n, wp.vec3), (n, wp.vec3), (n, wp.mat33), (n, wp.mat33)]

    def zero_grad(self) -> None:
        self._grads.zero()

    @property
    def arrays(self) -> tuple[wp.array, ...]:
        return (self.x, self.v, self.C, self.b)

    def copy_from(self, other: _State) -> None:
        for dst, src in zip(self.arrays, other.arrays, strict=True):
            wp.copy(dst, src)


class _Grid:
    """Grid arrays of one substep.

    Per (batch, object, node) fields and the effects' per-particle stress. Kernels read them as
    ``grid_<name>``.

    ``box`` is the box of nodes (lower corner, size) that the last substep on this grid ran over
    (``Simulator._active_box``; None before the first). Every write of a substep, and of its
    adjoint, to a per-node array lands inside its box: P2G scatters into the particles'
    stencils, the effects and the grid passes write at nodes with mass, and the adjoints write
    the gradients of what these read. Outside it the arrays and their gradients stay zero, so on
    the CPU ``zero`` and ``zero_grad`` clear that box only (about a tenth of the grid around a
    scene); elsewhere the box is the whole grid.

    ``clears`` (a grid without gradients on a GPU with more than ``CLEAR_NODES`` field nodes a
    particle, such as a search batch's, whose memset was an eighth of its substep): G2P clears
    what the next substep adds to, each particle its stress and the masses, momenta and
    accelerations of its stencil's nodes, which are every node that a substep gave mass to, and
    the whole grid is cleared once at each rollout's start (``Simulator._queue_rollout``, outside
    the captured graphs: velocities left non-finite by a rollout that diverged would otherwise
    reach G2P at a stencil's node of zero weight and no mass). The velocities are kept apart
    from the momenta there, as G2P reads them while it clears.

    Otherwise, without gradients and with one object, the velocities ``v`` are the momenta ``p``,
    overwritten: the grid update reads a node's momentum in the thread that writes its velocity,
    and nothing reads momenta after it. At a node without mass the momentum is zero too (every
    particle adds its mass and momentum with the same weight), so G2P reads what a zeroed ``v``
    held, and a substep clears a third less memory. A tape needs the momenta for the adjoint,
    and with several objects the grid update of one field reads the momenta of the others at
    its node (``kernels.grid_update``'s contact sums), so there ``v`` has its own. Where a grid
    keeps gradients on a device with vector reductions, that array is 16 bytes a node and ``v``
    the first three floats of each (``_slot_vectors``), so that G2P's adjoint adds a run's
    velocity adjoint with one vector reduction (``warp_reduce.add``); a search batch's grid,
    which has no adjoint, keeps 12 bytes a node.
    """

    def __init__(self, n_batch: int, n_objects: int, dims: tuple[int, int, int], n_particles: int,
                 stress: bool, device: str, requires_grad: bool, accelerated: bool = True,
                 memory: Memory | None = None, clears: bool = False) -> None:
        # the differentiable arrays (``arrays``) first, their gradients in an arena of their own
        interleaved = vector_reductions(device)
        (nodes, self.a, self.v, self.tau), self._values, self._grads = _arrays(
            self.specs(n_batch, n_objects, dims, n_particles, stress, accelerated, requires_grad, clears,
                       interleaved), device, requires_grad, memory)
        self.p, self.m = _momentum_and_mass(nodes, interleaved)
        if requires_grad:
            self.p.grad, self.m.grad = _momentum_and_mass(nodes.grad, interleaved)
        if self.v.dtype == wp.vec4:  # slots, only where gradients are kept (class docstring)
            slots = self.v
            self.v = _slot_vectors(slots)
            self.v.grad = _slot_vectors(slots.grad)
        if not self.own_velocities(n_objects, requires_grad, clears):
            self.v = self.p
        self.clears = int(clears)
        self.box: tuple[tuple[int, ...], tuple[int, ...]] | None = None
        self._cpu = device == "cpu"
        self._field_grid = (n_batch * n_objects, *dims)  # the per-node arrays seen as grids, one per field
        self._cleared: dict[bool, tuple[wp.array, list[np.ndarray]]] = {}

    @staticmethod
    def specs(n_batch: int, n_objects: int, dims: tuple[int, int, int], n_particles: int,
              stress: bool, accelerated: bool, requires_grad: bool, clears: bool,
              interleaved: bool) -> list[tuple[int, type]]:
        """The arrays' sizes and types.

        Momenta and masses in one array of 16 bytes a node (``_momentum_and_mass``);
        accelerations and stresses only where an effect adds them, velocities apart from the
        momenta only where ``own_velocities`` (16 bytes a node where ``interleaved`` and
        ``requires_grad``: class docstring). ``interleaved`` is ``vector_reductions``'s answer for
        the grid's device, which a frame tape's arena, sized from these specs, must share with
        the grids laid out in it.
        """
        n_grid = n_batch * n_objects * int(np.prod(dims))
        velocities = _Grid.own_velocities(n_objects, requires_grad, clears)
        return [(n_grid, wp.vec4), (n_grid if accelerated else 0, wp.vec3),
                (n_grid if velocities else 0, wp.vec4 if interleaved and requires_grad else wp.vec3),
                (n_particles if stress else 0, wp.mat33)]

    @staticmethod
    def own_velocities(n_objects: int, requires_grad: bool, clears: bool = False) -> bool:
        """Whether the velocities have an array of their own rather than overwrite the momenta (class docstring)."""
        return requires_grad or n_objects > 1 or clears

    @property
    def arrays(self) -> tuple[wp.array, ...]:
        """The differentiable arrays (their gradients are zeroed between frames)."""
        return self.m, self.p, self.a, self.v, self.tau

    def zero(self, box: tuple[tuple[int, ...], tuple[int, ...]]) -> None:
        """Zero every array for a substep that runs over ``box`` (see the class docstring)."""
        if self._cpu:
            self._zero(False)
        else:
            self._values.zero()
        self.box = box

    def clear(self) -> None:
        """Zero every array over the whole grid, whatever ``box`` says (a grid that G2P ``clears``)."""
        self._values.zero()
        self.box = None

    def zero_grad(self) -> None:
        """Zero the gradients of ``arrays`` (see the class docstring)."""
        if self._cpu:
            self._zero(True)
        else:
            self._grads.zero()

    def _zero(self, grads: bool) -> None:
        """On the CPU: zero the stresses, and the per-node arrays (or their ``grads``) in ``box``."""
        if grads not in self._cleared:
            self._cleared[grads] = self._clearing(grads)
        stress, grids = self._cleared[grads]
        stress.zero_()
        if self.box is not None:  # else as allocated
            lo, size = self.box
            inside = (slice(None), *(slice(start, start + n) for start, n in zip(lo, size, strict=True)))
            for grid in grids:
                grid[inside] = 0

    def _clearing(self, grads: bool) -> tuple[wp.array, list[np.ndarray]]:
        """What ``_zero`` clears of the values, or of their ``grads``.

        The stress array and the per-node arrays as numpy views shaped as grids (made once:
        making a view costs about what clearing a box does). Arrays no effect uses (empty) are
        left out.
        """
        fields = [self.m, self.p, self.a] + ([self.v] if self.v is not self.p else [])
        if grads:
            fields = [a.grad for a in fields]
        grids = [values.reshape(self._field_grid + values.shape[1:])
                 for values in (array.numpy() for array in fields if array.shape[0] > 0)]
        return self.tau.grad if grads else self.tau, grids


@dataclass
class _Command:
    """A recorded CPU launch (``Simulator._run``, ``Simulator._cpu_written``).

    The command, the arguments and the thread count it holds, and for ``_run`` the (index,
    name) of the arguments given by name at each launch.
    """

    command: wp.Launch
    args: list
    dim: int
    named: list[tuple[int, str]] = field(default_factory=list)

    def launch(self, values: Iterable[tuple[int, object]], dim: int) -> None:
        """Launch over ``dim`` threads with the (index, value) ``values`` set where they changed.

        Setting an argument costs about 4 us on the CPU, about what a substep's small kernels
        take to run; an array compares by identity.
        """
        for index, value in values:
            if value is not self.args[index] and value != self.args[index]:
                self.args[index] = value
                self.command.set_param_at_index(index, value)
        if dim != self.dim:
            self.dim = dim
            self.command.set_dim(dim)
        self.command.launch()


@dataclass(frozen=True)
class _Colliders:
    """What the grid update reads of the colliders (as ``collider_<name>``).

    Their ``count``; per collider c its shape code (``COLLIDER_SHAPES``), size and friction; per
    substep s of a frame and collider c, row s * count + c: position, rotation (world from
    collider), linear and angular velocity (allocated for a frame's substeps by
    ``Simulator._collider_poses``). One entry, unused, when there are none.
    """

    count: int
    shape: wp.array
    size: wp.array
    friction: wp.array
    pos: wp.array | None = None
    rot: wp.array | None = None
    vel: wp.array | None = None
    omega: wp.array | None = None


@dataclass(frozen=True)
class _OwnSteps:
    """Each batch row's substep (``dt``) and substeps per frame (``substeps``).

    The kernels read them as ``own_<name>``. A rollout at one time step gives every row the
    same of both; ``rollout(own_steps=True)`` gives each row its own (a row past its own
    substeps keeps its state until the frame's last).
    """

    dt: wp.array
    substeps: wp.array


ADJOINT_PARTS = 2
"""Parts that P2G's adjoint runs in, side by side, on the CPU (``Simulator._frame_adjoint``)."""
SPREAD_BLOCKS = 128
"""On a GPU, P2G and G2P take at least this many thread blocks where they have the warps for
them (``Simulator._spread``): about an H100's 132 multiprocessors."""
GRAPH_SUBSTEPS = 32
"""On a GPU, a frame's substeps run as captured graphs of at most this many substeps each
(``graph_runs``), which frames of every substep count share."""


def graph_runs(n_sub: int) -> list[tuple[int, int]]:
    """A frame's ``n_sub`` substeps as runs (first, count), each one captured graph on a GPU.

    A fit's substeps per frame change with its stiffness from one iteration to the next, and a
    graph of a whole frame, captured for one count, was seldom replayed: the frames of a fit
    launched their kernels one by one. The runs are ``GRAPH_SUBSTEPS`` long, and the rest falls
    into runs of halving powers of two, each starting at a multiple of its length, so that
    frames of every count share them (the kernels read the step from memory, not from their
    arguments: ``kernels``).
    """
    runs, first, size = [], 0, GRAPH_SUBSTEPS
    while first < n_sub:
        while first + size > n_sub:
            size //= 2
        runs.append((first, size))
        first += size
    return runs


def _graph_kind(key: tuple) -> tuple:
    """The kind of a graph's key (``Simulator._launch``): what it runs, less the substeps it runs them on.

    Keys of one kind launch the same kernels: ("kept", 0, 32) and ("kept", 160, 16) are both
    ("kept",), runs of recorded substeps; ("kept", "head", 183) is ("kept", "head").
    """
    return key[:2] if isinstance(key[1], str) else key[:1]


def _block_warps(n: int) -> int:
    """Warps of ``n`` particles a block on a GPU (``Simulator._spread``).

    The most of 1, 2, 4, 8 that leaves ``SPREAD_BLOCKS`` blocks or more, or 1 where the particles
    have fewer warps than that.
    """
    return min(kernels.BLOCK_WARPS, 1 << (max(-(-n // 32) // SPREAD_BLOCKS, 1).bit_length() - 1))


def _particle_threads(n: int, block_warps: int) -> int:
    """Threads of a launch over ``n`` particles with ``block_warps`` warps of them a block (``Simulator._spread``)."""
    if block_warps == kernels.BLOCK_WARPS:
        return n
    return -(-n // (32 * block_warps)) * kernels.BLOCK_WARPS * 32


def _p2g_planes(n: int) -> tuple[int, int]:
    """P2G's threads a particle on a GPU and its warps a block, for ``n`` particles (``kernels._p2g``).

    Three threads a particle where their blocks fit in one wave of P2G's adjoint: it takes 255
    registers a thread, so that one 256-thread block fills a multiprocessor's registers. The
    warps a block are the fewest that keep the blocks to ``SPREAD_BLOCKS``; with more particles,
    one thread a particle, spread as G2P (``_block_warps``).
    """
    for warps in (1, 2, 4, kernels.BLOCK_WARPS):
        if 3 * -(-n // (32 * warps)) <= SPREAD_BLOCKS:
            return 3, warps
    return 1, _block_warps(n)


CLEAR_NODES = 10
"""On a GPU, G2P clears a grid without gradients (``_Grid.clears``) where it has more than this
many field nodes a particle, and a memset clears it otherwise. On an H200 (benchmarks/RESULTS.md)
a memset cleared a field node in about 0.0066 ns and G2P's clearing added about 0.07 ns a
particle. Cleared by G2P, the search batches of thrown_ball and cube_on_slab (23 and 17 field
nodes a particle) took 9-10 % less time a substep and a batch of two small blocks (16) the
same; a batch of one small block (7) took 5 % more and one block of 1M particles (0.3) 13 %."""
SUBSTEP_HEADROOM = 1.15
"""On a GPU, a frame's tape buffers hold this many times the substeps first asked for."""
_G2P_ADJOINTS = ("src_x", "src_v", "src_C", "grid_v", "ground_height", "ground_normal", "dst_x", "dst_v",
                 "dst_C")
"""The arguments of ``kernels.g2p`` whose adjoints ``kernels.g2p_adjoint`` takes after them, in order."""
_P2G_ADJOINTS = ("src_x", "src_v", "src_C", "src_b", "volume", "grid_tau", "E", "nu", "yield_stress", "friction_angle",
                 "bulk_modulus", "viscosity", "density", "dst_b", "grid_m", "grid_p")
"""The arguments of ``kernels.p2g`` whose adjoints its written adjoint takes after them, in order
(``kernels.p2g_adjoint_kernel``)."""
_GRID_UPDATE_ADJOINTS = ("grid_m", "grid_p", "grid_a", "uniform", "friction", "ground_normal", "ground_friction",
                         "grid_v")
"""The arguments of the grid update whose adjoints its written adjoint takes after them, in order."""
_UNPACKED = object()
"""What ``Simulator._cpu_adjoint`` holds for an argument it has not packed yet."""


@dataclass
class _FrameTape:
    """The buffers of a frame recorded on a tape, for up to ``len(grids)`` substeps.

    A state per substep boundary and a grid per substep, their values in one allocation
    (``values``) and their gradients in another (``grads``), laid out state 0, grid 0, state 1,
    ... so that a frame of n substeps is the first ``prefix(n)`` bytes of each; the colliders'
    poses over the frame; and the tapes that last recorded a frame here, its head's (``"head"``)
    and each run's of substeps (``(first, count)``; ``Simulator._record_frame``).
    """

    states: list[_State]
    grids: list[_Grid]
    colliders: _Colliders
    values: wp.array
    grads: wp.array
    state_bytes: int
    grid_bytes: int
    tapes: dict[tuple[int, int] | str, wp.Tape] = field(default_factory=dict)

    def prefix(self, n_sub: int) -> int:
        """The bytes of a frame of ``n_sub`` substeps (values, or gradients)."""
        return (n_sub + 1) * self.state_bytes + n_sub * self.grid_bytes

    def words(self, n_sub: int) -> int:
        """``prefix`` in ``_Arena.WORD``s: what a copy of the frame's values counts."""
        return _Arena.raw(self.prefix(n_sub))[0]


def _bind(kernel: wp.Kernel, given: dict[str, object], scene: dict[str, object]) -> list:
    """The arguments of ``kernel``, each found by its parameter's name.

    A parameter takes, in this order: the value ``given`` under its name; field ``<field>`` of
    the bundle ``given`` as ``<bundle>`` when it is named ``<bundle>_<field>`` (a ``_State``
    as ``src``, ``dst`` or ``state``, a ``_Grid`` as ``grid``, the ``_Colliders`` as
    ``collider``, the ``_OwnSteps`` as ``own``); or the simulator's value of that name
    (``Simulator._scene``: sizes, grid geometry, per-particle and per-object constants, every
    parameter's replicas with its dots written as underscores, e.g. ``ground_height``). So the
    kernels' signatures are the only lists of their arguments. A parameter found nowhere, or a
    given value no parameter takes, is an error naming it.
    """
    args, used = [], set()
    for arg in kernel.adj.args:
        name = arg.label
        bundle, _, member = name.partition("_")
        if name in given:
            args.append(given[name])
            used.add(name)
        elif bundle in given and hasattr(given[bundle], member):
            args.append(getattr(given[bundle], member))
            used.add(bundle)
        elif name in scene:
            args.append(scene[name])
        else:
            raise TypeError(f"kernel {kernel.key}: no value for its parameter {name!r} (not given, "
                            f"not a field of a given bundle, not a simulator value)")
    unused = sorted(set(given) - used)
    if unused:
        raise TypeError(f"kernel {kernel.key} takes nothing from {', '.join(unused)}")
    return args


@wp.kernel
def _init_state(x0: wp.array(dtype=wp.vec3), v0: wp.array(dtype=wp.vec3), n_particles: int,
                state_x: wp.array(dtype=wp.vec3), state_v: wp.array(dtype=wp.vec3),
                state_C: wp.array(dtype=wp.mat33), state_b: wp.array(dtype=wp.mat33)):
    i = wp.tid()
    state_x[i] = x0[i % n_particles]
    state_v[i] = v0[i]
    state_C[i] = wp.mat33(0.0)
    state_b[i] = wp.identity(n=3, dtype=float)


@wp.kernel
def _to_callers(x: wp.array(dtype=wp.vec3), order: wp.array(dtype=int), n_particles: int,
                out: wp.array(dtype=wp.vec3)):
    """Positions from the simulator's particle order into the callers' (``SimConfig.cell_order``)."""
    i = wp.tid()
    first = (i // n_particles) * n_particles
    out[first + order[i - first]] = x[i]


@wp.kernel
def _from_callers(values: wp.array(dtype=wp.vec3), order: wp.array(dtype=int), n_particles: int,
                  out: wp.array(dtype=wp.vec3)):
    """Per-particle vectors from the callers' order into the simulator's (``_to_callers`` undone)."""
    i = wp.tid()
    first = (i // n_particles) * n_particles
    out[i] = values[first + order[i - first]]


@wp.kernel
def _add_vec3(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = a[i] + b[i]


@wp.kernel
def _add_floats(a: wp.array(dtype=float), b: wp.array(dtype=float), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = a[i] + b[i]


def kernel_modules(device: str, effects: Sequence[Effect] = ()) -> list[str]:
    """The modules of the kernels that a simulation on ``device`` with ``effects`` may launch (``load_kernels``).

    P2G with three threads a particle only on a GPU (``_p2g_planes``), and first: its module,
    with Warp's adjoint, takes the longest to build (7.8 s on an H200). The grid update and
    P2G's written adjoint are built for a scene's object count and families, each a module of
    its own that the simulator loads itself (the written adjoint at the first backward).
    """
    planes = [] if device == "cpu" else [kernels.p2g_planes.module.name]
    return list(dict.fromkeys([*planes, kernels.__name__, kernels.p2g.module.name, Parameters.__module__,
                               Effect.__module__, __name__, *(type(e).__module__ for e in effects)]))


def load_kernels(device: str, effects: Sequence[Effect] = ()) -> None:
    """Build and load every kernel a simulation on ``device`` with ``effects`` may launch.

    Built into the kernel cache when not there yet; before any launch (``sim.runtime`` says why).
    """
    device = resolve_device(device)
    load_modules(device, kernel_modules(device, effects))


class Simulator:
    """One scene, B parameter sets; see the module docstring."""

    def __init__(self, objects: Sequence[ObjectModel], particles: Particles, config: SimConfig,
                 n_batch: int = 1) -> None:
        self.objects = list(objects)
        self.config = config
        self.n_batch = int(n_batch)
        self.device = resolve_device(config.device)
        self._check_scene(particles)
        load_kernels(self.device, config.effects)
        self.n_particles = len(particles.x)
        self.n_objects = len(self.objects)
        self.dx = float(config.dx)
        lo = np.asarray(config.lo, dtype=np.float64)
        self.dims = tuple(int(n) for n in np.ceil((np.asarray(config.hi) - lo) / self.dx).astype(int) + 1)
        self.lo = lo
        self.hi = lo + (np.asarray(self.dims) - 1) * self.dx
        self.n_nodes = int(np.prod(self.dims))
        self._check_inside(particles)
        self._order = self._cell_order(particles.x, config.cell_order)
        given = particles  # the callers' order, which the setters below take
        if self._order is not None:
            particles = Particles(x=particles.x[self._order], volume=particles.volume[self._order],
                                  object_index=particles.object_index[self._order],
                                  v=particles.v[self._order])
            self._inverse = np.argsort(self._order)
            self._order_wp = wp.array(self._order.astype(np.int32), dtype=int, device=self.device)
        self.effects = list(config.effects)
        names = [e.name for e in self.effects]
        if len(set(names)) != len(names):
            raise ParameterError(f"effects must have distinct names, got {names}")

        specs = list(MATERIAL_PARAMS) + list(GROUND_PARAMS)
        for effect in self.effects:
            specs += effect.specs()
        families = [o.family for o in self.objects]
        self.params = Parameters(specs, self.n_batch, [o.name for o in self.objects], families,
                                 self.device)
        for name in MATERIAL_PARAMS:
            values = {o.name: o.params[name.name] for o in self.objects if name.name in o.params}
            if values:
                self.params.set(name.name, values)
        if config.ground is not None:
            self.params.update(config.ground.initial())
        for effect in self.effects:
            self.params.update({f"{effect.name}.{k}": v for k, v in effect.initial.items()})
        self.params.validate()  # the specs' defaults too; every later value is checked as it is set
        self._uniform_parts, self._uniform_sums = self._uniform_arrays()

        d = self.device
        self.obj = wp.array(particles.object_index, dtype=int, device=d)
        self.family = wp.array([FAMILY_CODES[o.family] for o in self.objects], dtype=int, device=d)
        # contact normals come from the larger object of a pair (kernels.grid_update)
        sizes = [particles.volume[particles.object_index == k].sum() for k in range(self.n_objects)]
        rank = np.empty(self.n_objects, dtype=np.int32)
        rank[np.argsort(sizes, kind="stable")] = np.arange(self.n_objects)
        self.normal_rank = wp.array(rank, dtype=int, device=d)
        self.ranked_object = wp.array(np.argsort(rank), dtype=int, device=d)
        self.x0 = wp.array(particles.x.astype(np.float32), dtype=wp.vec3, device=d)
        self.volume = wp.zeros(self.n_batch * self.n_particles, dtype=float, device=d,
                               requires_grad=True)
        self.v0 = wp.zeros(self.n_batch * self.n_particles, dtype=wp.vec3, device=d,
                           requires_grad=True)
        self._staging = _Staging(d)
        self.set_volume(given.volume)
        self.set_initial_velocity(given.v)
        self._setup_colliders()
        # the grid update for this many objects, without the colliders' code where there are none
        self._grid_update, grid_adjoint = kernels.grid_update_kernels(
            kernels.MAX_COLLIDERS if self.config.colliders else 0, self.n_objects)
        # P2G's written adjoint, for the scene's one family if it has one (kernels.p2g_adjoint_kernel)
        families = {FAMILY_CODES[model.family] for model in self.objects}
        p2g_adjoint = kernels.p2g_adjoint_kernel(families.pop() if len(families) == 1 else -1)
        # every kernel's adjoint is Warp's but these, written out (kernels.g2p_adjoint says why)
        self._written = {kernels.g2p: (kernels.g2p_adjoint, _G2P_ADJOINTS),
                         kernels.p2g: (p2g_adjoint, _P2G_ADJOINTS),
                         self._grid_update: (grid_adjoint, _GRID_UPDATE_ADJOINTS)}
        load_modules(self.device, [self._grid_update.module.name])
        # what the kernels read besides the bundles a launch passes (_bind); these arrays live
        # as long as the simulator (parameter values are written into their replicas)
        self._scene = {
            "n_particles": self.n_particles, "part": 0, "parts": 1, "n_objects": self.n_objects,
            "n_nodes": self.n_nodes,
            "dims": wp.vec3i(*self.dims), "lo": wp.vec3(*self.lo), "hi": wp.vec3(*self.hi),
            "dx": self.dx, "x0": self.x0, "v0": self.v0, "volume": self.volume, "obj": self.obj,
            "family": self.family, "normal_rank": self.normal_rank,
            "ranked_object": self.ranked_object, "has_ground": int(config.ground is not None),
            "uniform": self._uniform_sums[-1] if self._uniform_sums else self._uniform_parts[0],
            **{name.replace(".", "_"): self.params[name] for name in self.params.specs},
        }
        if self.device == "cpu":
            self._spread(kernels.BLOCK_WARPS)
        else:
            n = self.n_batch * self.n_particles
            self._spread(_block_warps(n), *_p2g_planes(n))
        self._stress = any(e.has_stress for e in self.effects)
        self._accelerated = any(e.has_accelerate for e in self.effects)
        self._record: dict | None = None
        self._final: _State | None = None
        self._queued = 0
        """Rollouts queued so far: a ``QueuedRollout`` waited for after a later one is refused."""
        self._buffers: tuple[list[_State], _Grid] | None = None
        self._tape_buffers: list[_FrameTape] | None = None
        self._adjoint_buffers: tuple[_State, wp.array] | None = None
        self._kept: list[wp.array] = []
        self._use_graphs = bool(config.cuda_graphs) and self.device.startswith("cuda")
        self._graphs: dict[tuple, wp.context.Graph] = {}
        self._loaded: set[tuple] = set()
        """The kinds of graph (``_graph_kind``) whose kernels a run has loaded (``_launch``)."""
        self._commands: dict[tuple, _Command] = {}
        self._box_args: tuple[tuple | None, dict[str, wp.vec3i]] = (None, {})
        """The last substep's box of grid nodes, and the launch arguments that give it."""
        # Warp's adjoints (kernel, hooks, packed parameters, packed values), and written ones
        self._adjoint_commands: dict[tuple, tuple] = {}
        self._written_commands: dict[tuple, _Command] = {}
        self._labels: dict[wp.Kernel, dict[str, int]] = {}
        self._steps = _OwnSteps(wp.zeros(self.n_batch, dtype=float, device=d),
                                wp.zeros(self.n_batch, dtype=int, device=d))

    # --- set-up and checks ----------------------------------------------------------------

    def _spread(self, block_warps: int, planes: int = 1, plane_warps: int | None = None) -> None:
        """Run P2G and G2P with ``block_warps`` warps of particles in each block of 256 threads.

        A small scene's particles fill few blocks (one row of a sample bag's 3,121: 13 blocks of
        an H100's 132 multiprocessors), and each block's eight warps share one multiprocessor's
        issue slots, caches and load/store units; spread out, a launch takes at least
        ``SPREAD_BLOCKS`` blocks where it has the warps for them. The threads past a block's
        warps return at once (``kernels.block_particle``). Every particle runs as before, so
        the results are the same (on the CPU, where the threads run in order, to the bit).
        ``block_warps`` is 1, 2, 4 or 8: so a lane's replicas follow its particle's, as the CPU
        adjoint's parts need (``params.lane_particle``). ``planes`` threads a particle (1 or 3)
        run P2G, with ``plane_warps`` warps of particles a block (``block_warps`` by default;
        ``kernels._p2g``, ``_p2g_planes``). Set before the first rollout: recorded commands and
        captured graphs keep the launches they were made with.
        """
        plane_warps = plane_warps or block_warps
        if block_warps not in (1, 2, 4, 8) or plane_warps not in (1, 2, 4, 8):
            raise ValueError(f"block_warps and plane_warps must be 1, 2, 4 or 8, not {block_warps}, {plane_warps}")
        if planes not in (1, 3):
            raise ValueError(f"planes must be 1 or 3, not {planes}")
        n = self.n_batch * self.n_particles
        self._scene["block_warps"], self._scene["plane_warps"] = block_warps, plane_warps
        self._particle_threads = _particle_threads(n, block_warps)
        plane_threads = _particle_threads(n, plane_warps)
        if planes > 1:  # whole blocks a plane, so that a warp's lanes scatter one plane
            plane_threads = -(-plane_threads // (kernels.BLOCK_WARPS * 32)) * kernels.BLOCK_WARPS * 32
        self._scene["plane_threads"] = plane_threads
        self._p2g = kernels.p2g_planes if planes > 1 else kernels.p2g
        self._p2g_threads = plane_threads * planes
        load_modules(self.device, [self._p2g.module.name])

    def _uniform_arrays(self) -> tuple[list[wp.array], list[wp.array]]:
        """The replicas of the uniform accelerations (``Effect.uniform``) and their running sums.

        The grid passes read the last sum (``kernels.field_velocity``), refreshed every frame by
        ``_replicate``; with one uniform effect, its own replicas; with none, zeros.
        """
        parts = []
        for effect in self.effects:
            if effect.uniform:
                spec = self.params.spec(f"{effect.name}.{effect.uniform}")
                if spec.size != 3 or spec.per_object:
                    raise ParameterError(f"effect {effect.name!r}: its uniform acceleration "
                                         f"{spec.name!r} must be one 3-vector per batch")
                parts.append(self.params[spec.name])
        if not parts:
            return [wp.zeros(self.n_batch * 3 * REPLICAS, dtype=float, device=self.device)], []
        return parts, [wp.zeros_like(parts[0], requires_grad=True) for _ in parts[1:]]

    def _replicate(self) -> None:
        """A frame's parameter replicas (``Parameters.replicate``) and uniform acceleration sums."""
        self.params.replicate()
        total = self._uniform_parts[0]
        for part, out in zip(self._uniform_parts[1:], self._uniform_sums, strict=True):
            wp.launch(_add_floats, dim=out.shape[0], inputs=[total, part], outputs=[out], device=self.device)
            total = out

    def _check_scene(self, particles: Particles) -> None:
        if not self.objects:
            raise ParameterError("a simulation needs at least one object")
        names = [o.name for o in self.objects]
        if len(set(names)) != len(names):
            raise ParameterError(f"object names must be distinct, got {names}")
        for o in self.objects:
            if o.family not in FAMILY_CODES:
                raise ParameterError(f"object {o.name!r}: unknown material family {o.family!r} "
                                     f"(expected one of {', '.join(FAMILY_CODES)})")
            unknown = sorted(set(o.params) - {s.name for s in MATERIAL_PARAMS})
            if unknown:
                raise ParameterError(f"object {o.name!r}: unknown parameter(s) {', '.join(unknown)}")
        index = particles.object_index
        if index.size and (index.min() < 0 or index.max() >= len(self.objects)):
            raise ParameterError(f"particle object_index must lie in 0..{len(self.objects) - 1}, "
                                 f"got {index.min()}..{index.max()}")
        empty = [o.name for k, o in enumerate(self.objects) if not np.any(index == k)]
        if empty:
            raise ParameterError(f"objects without particles: {', '.join(empty)}")
        if self.config.dx <= 0 or self.config.frame_dt <= 0 or not 0 < self.config.cfl <= 1:
            raise ParameterError("dx and frame_dt must be positive and cfl in (0, 1]")
        if len(self.config.colliders) > kernels.MAX_COLLIDERS:
            raise ParameterError(f"at most {kernels.MAX_COLLIDERS} colliders, got "
                                 f"{len(self.config.colliders)}")

    def _check_inside(self, particles: Particles) -> None:
        margin = (WALL_CELLS + 1) * self.dx
        for k, o in enumerate(self.objects):
            x = particles.x[particles.object_index == k]
            if np.any(x < self.lo + margin) or np.any(x > self.hi - margin):
                raise ParameterError(
                    f"object {o.name!r}: particles span {x.min(axis=0).round(4).tolist()}.."
                    f"{x.max(axis=0).round(4).tolist()} m, outside the simulation domain "
                    f"{(self.lo + margin).round(4).tolist()}..{(self.hi - margin).round(4).tolist()}"
                    f" m (the grid minus {WALL_CELLS + 1} wall cells); enlarge the domain")

    def _cell_order(self, x: np.ndarray, asked: bool | None) -> np.ndarray | None:
        """The particles' order sorted by ``_stencil_cells``, or None to keep the given one.

        ``asked``: ``SimConfig.cell_order``; by default the cells are not even computed on the CPU.
        """
        if asked is False or (asked is None and not self.device.startswith("cuda")):
            return None
        cells = self._stencil_cells(x)
        if asked is None and cell_lines(cells) >= SORT_LINES:
            return None
        return np.argsort(cells, kind="stable")

    def _stencil_cells(self, x: np.ndarray) -> np.ndarray:
        """The grid cell (linear index) where each particle's stencil starts.

        Sorted by it (``SimConfig.cell_order``), particles are kept in that order inside the
        simulator, and every array that goes in or out per particle (initial velocities and
        volumes, states, trajectories, dL/dx and gradients) is permuted at the boundary, so
        callers never see it. Neighbouring lanes of a warp then share their stencil, and P2G's
        scatter adds once per run of them (``sim.warp_reduce``). Measured on an H200 (benchmarks/
        RESULTS.md): particles given in random order took 3x as long per substep as sorted ones
        at 100k and 1M particles. One block on a lattice (two particles to a cell along its
        fastest axis, as ``sim.sampling`` makes it) of 97k or 1M particles, whose lines run 46
        and 100 particles, ran 9-31 % slower sorted than as given; the search batches of
        lifted sample bags (lines of 6-8 particles) and of 32 blocks of 2,744 (lines of 14) were
        up to 21 % faster sorted, or the same. Hence ``SORT_LINES``. On the CPU a launch's
        threads run in order without contention, and the given order is kept by default.
        """
        cell = np.clip(np.floor((x - self.lo) / self.dx - 0.5), 0, np.asarray(self.dims) - 3)
        cell = cell.astype(np.int64)
        return (cell[:, 0] * self.dims[1] + cell[:, 1]) * self.dims[2] + cell[:, 2]

    def _inward(self, values: np.ndarray, axis: int = 1) -> np.ndarray:
        """Per-particle values (particles along ``axis``) from the callers' order into ours."""
        return values if self._order is None else np.take(values, self._order, axis=axis)

    def _outward(self, values: np.ndarray, axis: int = 1) -> np.ndarray:
        """Per-particle values (particles along ``axis``) from our order into the callers'."""
        return values if self._order is None else np.take(values, self._inverse, axis=axis)

    def _setup_colliders(self) -> None:
        d, colliders = self.device, self.config.colliders
        shapes = [COLLIDER_SHAPES[c.shape] for c in colliders] or [0]
        sizes = [tuple(c.size) + (0.0,) * (3 - len(c.size)) for c in colliders] or [(0.0,) * 3]
        self._colliders = _Colliders(
            count=len(colliders), shape=wp.array(shapes, dtype=int, device=d),
            size=wp.array(np.array(sizes, dtype=np.float32), dtype=wp.vec3, device=d),
            friction=wp.array([c.friction for c in colliders] or [0.0], dtype=float, device=d))

    def _collider_poses(self, frame: int, n_sub: int, dt: float) -> None:
        """Fill the collider pose arrays of the rollouts for one frame (``_pose_colliders``)."""
        rows = n_sub * len(self.config.colliders) or 1
        held = self._colliders.pos.shape[0] if self._colliders.pos is not None else 0
        if rows > held:  # room for more, as the tape buffers have (their docstring)
            self._colliders = self._collider_arrays(self._capacity(n_sub))
            self._forget_graphs("frame")
        self._pose_colliders(self._colliders, frame, n_sub, dt)

    def _collider_arrays(self, n_sub: int) -> _Colliders:
        """The colliders with pose arrays of their own for a frame of ``n_sub`` substeps."""
        rows, d = n_sub * len(self.config.colliders) or 1, self.device
        return replace(self._colliders, pos=wp.zeros(rows, dtype=wp.vec3, device=d),
                       rot=wp.zeros(rows, dtype=wp.quat, device=d),
                       vel=wp.zeros(rows, dtype=wp.vec3, device=d),
                       omega=wp.zeros(rows, dtype=wp.vec3, device=d))

    def _pose_colliders(self, target: _Colliders, frame: int, n_sub: int, dt: float) -> None:
        """Fill ``target``'s pose arrays (one row per substep and collider) for one frame."""
        colliders = self.config.colliders
        if not colliders:
            return
        t0 = frame * self.config.frame_dt
        rows = target.pos.shape[0] // len(colliders)  # n_sub or more (the rows past n_sub unused)
        pos = np.zeros((rows, len(colliders), 3), np.float32)
        rot = np.zeros((rows, len(colliders), 4), np.float32)
        vel = np.zeros((rows, len(colliders), 3), np.float32)
        omega = np.zeros((rows, len(colliders), 3), np.float32)
        for s in range(n_sub):
            for c, collider in enumerate(colliders):
                t = t0 + s * dt
                pos[s, c], rot[s, c] = collider.pose(t)
                vel[s, c], omega[s, c] = collider.velocity(t)
        target.pos.assign(pos.reshape(-1, 3))
        target.rot.assign(rot.reshape(-1, 4))
        target.vel.assign(vel.reshape(-1, 3))
        target.omega.assign(omega.reshape(-1, 3))

    def set_initial_velocity(self, v: np.ndarray) -> None:
        """Initial particle velocities, (N, 3) for every batch or (B, N, 3)."""
        v = np.broadcast_to(np.asarray(v, dtype=np.float32),
                            (self.n_batch, self.n_particles, 3))
        if not np.all(np.isfinite(v)):
            raise ParameterError("initial velocities must be finite")
        self.v0.assign(np.ascontiguousarray(self._inward(v)).reshape(-1, 3))
        # each row's fastest particle, for the time step (read back from the device, a million
        # particles' speeds took 25 ms of every rollout)
        self._v0_speed = np.max(np.linalg.norm(v, axis=2), axis=1, initial=0.0)

    def initial_velocity(self) -> np.ndarray:
        """The initial particle velocities (B, N, 3) that ``set_initial_velocity`` set."""
        return self._outward(self._staging.download(self.v0).reshape(self.n_batch, self.n_particles, 3))

    def initial_positions(self) -> np.ndarray:
        """The particles' initial positions (N, 3), float32 as simulated."""
        return self._outward(self._staging.download(self.x0)[None])[0]

    def object_index(self) -> np.ndarray:
        """Each particle's object (N,), an index into ``objects``."""
        return self._outward(self._staging.download(self.obj)[None])[0]

    def volumes(self) -> np.ndarray:
        """The particle volumes (B, N) that ``set_volume`` set."""
        return self._outward(self._staging.download(self.volume).reshape(self.n_batch, self.n_particles))

    def set_volume(self, volume: np.ndarray) -> None:
        """Particle volumes (m^3), (N,) for every batch or (B, N)."""
        volume = np.broadcast_to(np.asarray(volume, dtype=np.float32),
                                 (self.n_batch, self.n_particles))
        if np.any(~np.isfinite(volume)) or np.any(volume < 0):
            raise ParameterError("particle volumes must be finite and non-negative")
        self.volume.assign(np.ascontiguousarray(self._inward(volume)).ravel())

    @property
    def kept_tape_frames(self) -> int:
        """Frames whose tapes the simulator holds from a ``grad=True`` rollout (``SimConfig.tape_memory``).

        0 where the backward recomputes every frame (the CPU, or a window that did not fit);
        blocks are kept for later rollouts of as many frames or fewer.
        """
        return len(self._kept)

    # --- time stepping --------------------------------------------------------------------

    def time_step(self, substeps: int | None = None) -> tuple[int, float]:
        """(substeps per frame, dt) for the current parameters of every batch.

        ``substeps`` forces a count (e.g. to compare rollouts at fixed discretisation, as a
        finite-difference check must); it is refused when below the stability bound.
        """
        return self._time_step(slice(None), substeps)

    def own_time_steps(self) -> tuple[np.ndarray, np.ndarray]:
        """Each batch row's own (substeps per frame, dt), as a simulator of that row alone has them.

        ``rollout(own_steps=True)`` steps each row so.
        """
        steps = [self._time_step(slice(b, b + 1)) for b in range(self.n_batch)]
        return np.array([n for n, _ in steps]), np.array([dt for _, dt in steps])

    def _time_step(self, rows: slice, substeps: int | None = None) -> tuple[int, float]:
        """``time_step`` of the batch rows ``rows``."""
        speeds = [0.0]
        for k, o in enumerate(self.objects):
            values = {s.name: self.params.get(s.name)[rows, k] for s in MATERIAL_PARAMS}
            speeds.append(float(np.max(wave_speed(o.family, values))))
        v0_max = float(np.max(self._v0_speed[rows], initial=0.0))
        dt = self.config.cfl * self.dx / (max(speeds) + self.config.max_speed + v0_max)
        # Explicit viscosity: nu dt / dx^2 <= 1 / (2 d), d = 3
        rho = self.params.get("density")[rows]
        for k, o in enumerate(self.objects):
            if o.family == "fluid":
                eta = self.params.get("viscosity")[rows, k]
                if np.any(eta > 0):
                    dt = min(dt, float(np.min(rho[:, k] * self.dx**2 / (6.0 * np.maximum(eta, 1e-30)))))
        for effect in self.effects:
            values = {s.name: self.params.get(f"{effect.name}.{s.name}")[rows] for s in effect.params}
            dt = min(dt, effect.time_step_limit(values, self.dx, float(np.min(rho))))
        n_sub = math.ceil(self.config.frame_dt / dt - 1e-9)
        if substeps is not None:
            if substeps < n_sub:
                raise ParameterError(f"substeps={substeps} per frame is below the stability bound "
                                     f"of {n_sub} for these parameters")
            n_sub = int(substeps)
        if n_sub > self.config.max_substeps:
            raise ParameterError(
                f"the time step bound ({dt:.3g} s) needs {n_sub} substeps per frame, more than "
                f"max_substeps={self.config.max_substeps}; lower the stiffness or raise dx")
        return n_sub, self.config.frame_dt / n_sub

    def _values(self, effect: Effect) -> dict[str, wp.array]:
        return {s.name: self.params[f"{effect.name}.{s.name}"] for s in effect.params}

    def _labels_of(self, kernel: wp.Kernel) -> dict[str, int]:
        """The position of each of ``kernel``'s arguments, by name."""
        labels = self._labels.get(kernel)
        if labels is None:
            labels = self._labels[kernel] = {arg.label: i for i, arg in enumerate(kernel.adj.args)}
        return labels

    def _run(self, kernel: wp.Kernel, dim: int, **given: object) -> None:
        """Launch ``kernel`` over ``dim`` threads with its arguments found by name (``_bind``).

        On the CPU a launch repeats a recorded command (``wp.Launch``) of the same kernel and
        bundles, with the values given by name set anew where they changed since its last
        launch: packing all of a kernel's arguments costs 12-50 us, about what a substep's small
        kernels take to run, and setting one about 4 us. The command keeps its bundles, so their
        arrays outlive it. On a tape (``wp.context.runtime.tape``, the one ``wp.launch`` records
        on) the launch is recorded as ``wp.launch`` records it.
        """
        if self.device != "cpu":
            wp.launch(kernel, dim=dim, inputs=_bind(kernel, given, self._scene), device=self.device)
            return
        labels = self._labels_of(kernel)
        # a given value that is a parameter is set at a launch; a bundle picks the command
        key = (kernel, *((name, None if name in labels else value) for name, value in given.items()))
        recorded = self._commands.get(key)
        if recorded is None:
            args = _bind(kernel, given, self._scene)
            command = wp.launch(kernel, dim=dim, inputs=args, device=self.device, record_cmd=True)
            recorded = self._commands[key] = _Command(command, args, dim,
                                                      [(labels[n], n) for n in given if n in labels])
        recorded.launch(((index, given[name]) for index, name in recorded.named), dim)
        tape = wp.context.runtime.tape
        if tape is not None:
            tape.record_launch(kernel, dim, 0, list(recorded.args), [], self.device)

    def _substep(self, src: _State, dst: _State, grid: _Grid, row: int,
                 colliders: _Colliders | None = None, cleared: bool = False) -> None:
        """One MLS-MPM substep from ``src`` to ``dst`` (docs/simulator.md maps it to the method).

        ``row`` is the substep's index in its frame (which of the poses of ``colliders``, by
        default the rollouts', apply). Each batch row's step is ``_set_steps``'. ``cleared``:
        ``grid`` is zero already (``_record_frame``).
        """
        d, B, N, K, G = self.device, self.n_batch, self.n_particles, self.n_objects, self.n_nodes
        box_lo, box_dims = self._active_box(src)
        if cleared or grid.clears:  # (``_Grid``'s docstring)
            grid.box = (box_lo, box_dims)
        else:
            grid.zero((box_lo, box_dims))
        if self._stress:
            view = ParticleView(src.x, src.v, src.C, src.b, self.obj, grid.tau, B, N, K, d)
            for effect in self.effects:
                if effect.has_stress:
                    effect.stress(view, self._values(effect))
        self._run(self._p2g, self._p2g_threads, src=src, dst=dst, grid=grid, substep=row, own=self._steps)
        view = GridView(grid.m, grid.p, grid.a, B, K, G, self.dims, self.lo, self.dx, d, box_lo, box_dims)
        for effect in self.effects:
            if effect.has_accelerate:
                effect.accelerate(view, self._values(effect))
        n_box = view.n_box
        if self._box_args[0] != (box_lo, box_dims):  # the same objects while the box stays (``_run``)
            self._box_args = ((box_lo, box_dims), {"box_lo": wp.vec3i(*box_lo), "box_dims": wp.vec3i(*box_dims)})
        box = self._box_args[1]
        self._run(self._grid_update, n_box, grid=grid, collider=colliders or self._colliders, substep=row,
                  **box, own=self._steps)
        self._run(kernels.g2p, self._particle_threads, src=src, dst=dst, grid=grid, substep=row, own=self._steps)

    def _active_box(self, state: _State) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """Lower corner and size (nodes) of the box of grid nodes the grid passes run over.

        On a CUDA device the whole grid: a thread per node costs little there, and a box read
        back every substep would stall the device and break the captured graphs. On the CPU
        every thread costs, and the grid around a scene is mostly empty: there it is the box of
        nodes that the particles' quadratic stencils reach, one node wider on every side for the
        float32 rounding of the stencil's corner (``kernels.stencil_base``, whose clamp it
        repeats). The passes skip empty nodes either way, and the CPU runs a launch's threads in
        order, so the results are the same to the last bit.
        """
        if self.device != "cpu":
            return (0, 0, 0), self.dims
        x = np.ascontiguousarray(state.x.numpy().T)  # a row reduces 20x faster than a column
        low, high = x.min(axis=1).tolist(), x.max(axis=1).tolist()  # float64, as Python floats
        if not all(map(math.isfinite, low + high)):
            return (0, 0, 0), self.dims  # a diverging state: leave it to the frame's check
        box_lo, box_dims = [], []
        for first, last, corner, n in zip(low, high, self.lo.tolist(), self.dims, strict=True):
            top = n - 3  # in float64 and in this order, as the stencil's corner is clamped
            base = [min(max(math.floor((v - corner) / self.dx - 0.5), 0), top) for v in (first, last)]
            box_lo.append(max(base[0] - 1, 0))
            box_dims.append(min(base[1] + 3, top + 2) - box_lo[-1] + 1)  # the stencil's last node, plus one
        return tuple(box_lo), tuple(box_dims)

    def _set_steps(self, dt: float | np.ndarray, substeps: int | np.ndarray) -> None:
        """Every batch row's substep and substeps a frame, where the kernels read them (``_OwnSteps``).

        One value for every row (a rollout at one time step), or an array of one per row.
        """
        if np.ndim(dt):
            self._steps.dt.assign(np.asarray(dt, dtype=np.float32))
        else:
            self._steps.dt.fill_(dt)
        if np.ndim(substeps):
            self._steps.substeps.assign(np.asarray(substeps, dtype=np.int32))
        else:
            self._steps.substeps.fill_(int(substeps))

    def _runs(self, n_sub: int) -> list[tuple[int, int]]:
        """A frame's substeps as runs (first, count): ``graph_runs`` with CUDA graphs, else the frame."""
        return graph_runs(n_sub) if self._use_graphs else [(0, n_sub)]

    def _frame(self, states: list[_State], current: int, grid: _Grid, n_sub: int) -> int:
        """One frame's substeps from ``states[current]``, ping-ponging between the two states; where it ends."""
        self._launch(("frame", "replicate"), self._replicate)
        for first, size in self._runs(n_sub):
            at = (current + first) % 2
            self._launch(("frame", first, size, at), partial(self._substeps, states, at, grid, first, size))
        return (current + n_sub) % 2

    def _substeps(self, states: list[_State], current: int, grid: _Grid, first: int, size: int) -> None:
        """Substeps ``first`` to ``first + size - 1`` of a frame from ``states[current]`` (``_frame``)."""
        for s in range(first, first + size):
            self._substep(states[current], states[1 - current], grid, s)
            current = 1 - current

    def _record_frame(self, frame: _FrameTape, n_sub: int) -> None:
        """Compute one frame from ``frame.states[0]`` on tapes: its head's and each run's (``_runs``).

        Its gradients are not cleared here: a backward that recomputes the frame clears them
        first (``_zero_frame_grad``), a kept frame's adjoint just before it runs.
        """
        self._launch(("kept", "head", n_sub), partial(self._record_head, frame, n_sub))
        for first, size in self._runs(n_sub):
            self._launch(("kept", first, size), partial(self._record_run, frame, first, size))

    def _record_head(self, frame: _FrameTape, n_sub: int) -> None:
        """A recorded frame's clearing and, on its head's tape, its parameter replicas.

        On a GPU one memset clears every grid of the frame (and the states after the first,
        which the substeps overwrite), where a memset per substep had cost three times as long;
        the CPU clears each grid's box (``_Grid.zero``).
        """
        if self.device != "cpu":
            after, word = _Arena.raw(frame.prefix(n_sub) - frame.state_bytes)
            wp.array(ptr=frame.values.ptr + frame.state_bytes, dtype=word, shape=(after,),
                     device=self.device, owner=False).zero_()
        tape = frame.tapes["head"] = wp.Tape()
        with tape:
            self._replicate()

    def _record_run(self, frame: _FrameTape, first: int, size: int) -> None:
        """Substeps ``first`` to ``first + size - 1`` of a recorded frame, on the run's tape."""
        tape = frame.tapes[(first, size)] = wp.Tape()
        with tape:
            for s in range(first, first + size):
                self._substep(frame.states[s], frame.states[s + 1], frame.grids[s], s, frame.colliders,
                              cleared=self.device != "cpu")

    def _zero_frame_grad(self, frame: _FrameTape) -> None:
        """Clear the gradients of ``frame``'s states and grids.

        Before a recomputation moves the grids' boxes: ``_Grid.zero_grad`` clears the box of the
        substep that last ran on a grid, where the adjoint of that substep wrote; on a GPU the
        box is the grid, and one memset clears all.
        """
        if self.device != "cpu":
            frame.grads.zero_()
            return
        for state in frame.states:
            state.zero_grad()
        for grid in frame.grids:
            grid.zero_grad()

    def _frame_adjoint(self, frame: _FrameTape, n_sub: int, adjoint: _State, seed: wp.array,
                       helper: ThreadPoolExecutor | None = None) -> None:
        """Carry ``adjoint`` back over a frame of ``n_sub`` substeps recorded on ``frame``.

        ``adjoint`` holds dL/d(state) at the end of the frame (without the frame's own dL/dx,
        which is in ``seed``) and leaves holding dL/d(state) at its start. Nothing here records
        on a tape, so another thread may record the next frame meanwhile (``backward``). On the
        CPU, P2G's adjoint runs in ``ADJOINT_PARTS`` parts, the others on ``helper``'s thread
        (``kernels.p2g`` says why it may).
        """
        self._launch(("adjoint", "seed", n_sub), partial(self._seed_adjoint, frame, n_sub, adjoint, seed))
        for run in reversed(self._runs(n_sub)):
            self._launch(("adjoint", *run), partial(self._tape_adjoint, frame, run, helper))
        self._launch(("adjoint", "head"), partial(self._head_adjoint, frame, adjoint, helper))

    def _seed_adjoint(self, frame: _FrameTape, n_sub: int, adjoint: _State, seed: wp.array) -> None:
        """Start a frame's adjoint (``_frame_adjoint``): the replicas' gradients cleared, the last state's set."""
        self.params.zero_replica_grad()
        for total in self._uniform_sums:
            total.grad.zero_()
        last = frame.states[n_sub]
        wp.launch(_add_vec3, dim=self.n_batch * self.n_particles, inputs=[adjoint.x, seed],
                  outputs=[last.x.grad], device=self.device, record_tape=False)
        wp.copy(last.v.grad, adjoint.v)
        wp.copy(last.C.grad, adjoint.C)
        wp.copy(last.b.grad, adjoint.b)

    def _tape_adjoint(self, frame: _FrameTape, key: tuple[int, int] | str, helper: ThreadPoolExecutor | None) -> None:
        """The adjoints of the launches on ``frame``'s tape ``key`` (a run's, or ``"head"``), last first."""
        tape = frame.tapes[key]
        # tape.backward() less its recording: its adjoint launches would land on a tape that
        # another thread records
        for position, launch in enumerate(reversed(tape.launches)):
            if callable(launch):
                launch()
                continue
            self._adjoint_of(launch, tape, (id(frame), key, position), helper)

    def _head_adjoint(self, frame: _FrameTape, adjoint: _State, helper: ThreadPoolExecutor | None) -> None:
        """End a frame's adjoint: the head's (replicas' gradients into the parameters'), dL/d(state) at its start."""
        self._tape_adjoint(frame, "head", helper)
        for dst, src in zip(adjoint.arrays, frame.states[0].arrays, strict=True):
            wp.copy(dst, src.grad)

    def _adjoint_of(self, launch: tuple, tape: wp.Tape, key: tuple,
                    helper: ThreadPoolExecutor | None = None) -> None:
        """The adjoint of one ``launch`` recorded on ``tape`` (``_adjoint_launch``'s ``key``, ``helper``).

        G2P's, the grid update's and P2G's with one thread a particle are written out
        (``self._written``), every other kernel's Warp's.
        """
        kernel, dim, max_blocks, inputs, outputs = launch[:5]
        args = [*inputs, *outputs]
        written = self._written.get(kernel)
        if written is not None:
            adjoint, names = written
            labels = self._labels_of(kernel)
            adjoints = [tape.get_adjoint(args[labels[name]]) for name in names]
            self._adjoint_launch(key, adjoint, dim, max_blocks, [*args, *adjoints], tape, helper, written=True)
        else:
            self._adjoint_launch(key, kernel, dim, max_blocks, args, tape, helper)

    def _adjoint_launch(self, key: tuple, kernel: wp.Kernel, dim: int, max_blocks: int, args: list,
                        tape: wp.Tape, helper: ThreadPoolExecutor | None = None, written: bool = False) -> None:
        """Warp's adjoint of a launch of ``kernel`` with ``args``, or ``kernel`` itself if ``written``.

        A written adjoint (``kernels.g2p_adjoint``, P2G's, the grid update's) is a kernel of its own that
        takes the adjoints among its arguments. On the CPU a kernel with ``part`` and ``parts`` arguments
        (P2G) runs in ``ADJOINT_PARTS`` parts, the others on ``helper``'s thread
        (``params.lane_particle`` says why they may), each under a ``key`` of its own.
        """
        if self.device != "cpu":
            if written:
                wp.launch(kernel, dim, inputs=args, device=self.device, record_tape=False, max_blocks=max_blocks)
            else:
                wp.launch(kernel, dim, inputs=args, adj_inputs=[tape.get_adjoint(a) for a in args],
                          device=self.device, adjoint=True, record_tape=False, max_blocks=max_blocks)
            return
        run = self._cpu_written if written else self._cpu_adjoint
        labels = self._labels_of(kernel)
        if helper is None or "parts" not in labels:
            run(key, kernel, dim, args, tape)
            return
        jobs, plane_threads = [], args[labels["plane_threads"]]
        for part in range(ADJOINT_PARTS):
            args = list(args)
            args[labels["part"]], args[labels["parts"]] = part, ADJOINT_PARTS
            # each plane of the stencil (``kernels._p2g``) takes this part's lanes
            args[labels["plane_threads"]] = lane_count(plane_threads, part, ADJOINT_PARTS)
            threads = dim // plane_threads * args[labels["plane_threads"]]
            jobs.append(partial(run, (*key, part), kernel, threads, args, tape))
        others = [helper.submit(job) for job in jobs[1:]]
        jobs[0]()
        for other in others:
            other.result()

    def _cpu_written(self, key: tuple, kernel: wp.Kernel, dim: int, args: list, tape: wp.Tape) -> None:
        """Launch the written adjoint ``kernel`` with ``args`` on the CPU (``tape`` unused).

        Its command is kept under ``key`` and an argument is set again only where it changed
        (``_Command``), as ``_cpu_adjoint`` does for Warp's adjoints.
        """
        if dim == 0:  # a part of a launch that has no particles (``params.lane_count``): nothing to run
            return
        kept = self._written_commands.get(key)
        if kept is None or kept.command.kernel is not kernel:
            command = wp.launch(kernel, dim, inputs=args, device=self.device, record_tape=False, record_cmd=True)
            kept = self._written_commands[key] = _Command(command, list(args), dim)
        kept.launch(enumerate(args), dim)

    def _cpu_adjoint(self, key: tuple, kernel: wp.Kernel, dim: int, args: list, tape: wp.Tape) -> None:
        """Run the adjoint of one recorded CPU launch of ``kernel`` with arguments ``args``.

        As ``wp.launch(..., adjoint=True)`` does, but the packed arguments are kept under ``key``
        (a frame's buffers and the launch's place on its tape: every frame of a backward pass
        launches the same kernels on the same arrays) and only an argument that is not the
        object packed last time is packed again: packing a kernel's arguments and their
        adjoints costs about what a substep's small kernels take to run (``_run``).
        """
        kept = self._adjoint_commands.get(key)  # a key's place on a tape may hold another kernel now
        if kept is None or kept[0] is not kernel:
            hooks = kernel.module.load(self.device).get_kernel_hooks(kernel)
            kept = self._adjoint_commands[key] = (kernel, hooks, [None] * (1 + 2 * len(args)),
                                                  [_UNPACKED] * len(args))
        _, hooks, params, packed = kept
        for i, (spec, value) in enumerate(zip(kernel.adj.args, args, strict=True)):
            if value is not packed[i]:
                params[1 + i] = wp.context.pack_arg(kernel, spec.type, spec.label, value, self.device, False)
                params[1 + len(args) + i] = wp.context.pack_arg(kernel, spec.type, spec.label,
                                                                tape.get_adjoint(value), self.device, True)
                packed[i] = value
        params[0] = wp.types.launch_bounds_t(dim)
        hooks.backward(*params)

    def _launch(self, key: tuple, body: Callable[[], None]) -> None:
        """Run ``body`` (device work on the simulator's long-lived arrays only).

        With CUDA graphs, the first run of a kind of graph (``_graph_kind``) launches its kernels
        one by one, which also loads them (a module cannot load during a capture); every key
        after it, of that kind, is captured as a graph on its first run, which it and later runs
        replay. A fit meets new keys as its substeps change (``graph_runs``); captured where they
        are first seen, each costs the host one recording instead of a run one launch at a time
        and then a recording (docs/simulator.md, "CUDA graphs").
        """
        if not self._use_graphs:
            body()
            return
        graph = self._graphs.get(key)
        if graph is None:
            kind = _graph_kind(key)
            if kind not in self._loaded:
                body()
                self._loaded.add(kind)  # once it ran: a run that stopped part-way loaded part of it
                return
            # No garbage collection while capturing: collecting another simulator's graph
            # destroys it, which CUDA forbids during a capture and which then fails this one.
            collecting = gc.isenabled()
            gc.disable()
            wp.capture_begin(device=self.device, force_module_load=False)
            try:
                body()
            finally:
                graph = wp.capture_end(device=self.device)
                if collecting:
                    gc.enable()
            self._graphs[key] = graph
        wp.capture_launch(graph)

    def _forget_graphs(self, *kinds: str) -> None:
        """Drop the recorded commands and the captured graphs of ``kinds`` (their keys' first item).

        The arrays they ran on are being replaced: a rollout's colliders (``"frame"``), or the
        tape's buffers (``"kept"``, ``"adjoint"``).
        """
        for key in [key for key in self._graphs if key[0] in kinds]:
            del self._graphs[key]
        self._commands.clear()
        self._adjoint_commands.clear()
        self._written_commands.clear()

    def _check(self, state: _State, stats: wp.array) -> None:
        """Launch the state check of one frame into ``stats`` (B * K * 4, see ``_diverged``)."""
        self._run(kernels.check_state, self.n_batch * self.n_particles, state=state, stats=stats)

    def _diverged(self, stats: np.ndarray, frame: int, dt: float | np.ndarray) -> None:
        """Raise ``SimulationDiverged`` at the first frame, row and object whose check statistics say so.

        ``stats``: the statistics of one frame, ``frame``, or of consecutive frames from it
        (each ``4 B K`` floats); ``dt``: each row's, or all rows'. Checked as arrays: a search
        rollout's 30 frames of 32 rows of 2 objects took 1.7 ms of host time an element
        at a time, 0.03 ms as arrays.
        """
        stats = stats.reshape(-1, self.n_batch, self.n_objects, 4)
        row_dt = np.broadcast_to(np.asarray(dt, dtype=np.float64), (self.n_batch,))
        limits = (self.dx / row_dt).astype(np.float32)
        speed, bad, outside, det = np.moveaxis(stats, -1, 0)
        failed = (bad > 0) | (speed > limits[None, :, None]) | (det <= 1e-6) | (outside > 0)
        if not failed.any():
            return
        f, b, k = (int(i) for i in np.argwhere(failed)[0])
        speed, bad, outside, det = stats[f, b, k]
        if bad > 0:
            reason = f"{int(bad)} particle(s) have non-finite positions, velocities or deformation"
        elif speed > limits[b]:
            reason = f"speed {speed:.3g} m/s exceeds one grid cell per substep ({limits[b]:.3g} m/s)"
        elif det <= 1e-6:
            reason = f"the deformation inverted (det b = {det:.3g})"
        else:
            reason = f"{int(outside)} particle(s) left the simulation domain; enlarge it"
        o = self.objects[k]
        values = ", ".join(f"{n}={self.params.get(n)[b, k]:.4g}" for n in ("E", "nu", "density") if o.family != "fluid")
        raise SimulationDiverged(frame + f, o.name, b,
                                 f"{reason} ({o.family}{'; ' + values if values else ''}; dt={row_dt[b]:.3g} s, "
                                 f"dx={self.dx:g} m)")

    # --- rollouts and gradients ------------------------------------------------------------

    def _assign_state(self, state: _State, given: SimState) -> None:
        B, N = self.n_batch, self.n_particles
        for array, values, width in zip(state.arrays, (given.x, given.v, given.C, given.b),
                                        (3, 3, 9, 9), strict=True):
            values = np.broadcast_to(np.asarray(values, dtype=np.float32),
                                     (B, N) + ((3,) if width == 3 else (3, 3)))
            array.assign(np.ascontiguousarray(self._inward(values)).reshape(B * N, *values.shape[2:]))

    def _initial_state(self, state: _State) -> None:
        self._run(_init_state, self.n_batch * self.n_particles, state=state)

    def _seed_from(self, values: wp.array, frame: int, seed: wp.array) -> None:
        """Copy frame ``frame`` of ``values`` (frames of B N ``wp.vec3``, the callers' order) into ``seed``, in ours."""
        n = self.n_batch * self.n_particles
        if self._order is None:
            wp.copy(seed, values, src_offset=frame * n, count=n)
        else:
            wp.launch(_from_callers, dim=n, inputs=[values[frame * n:(frame + 1) * n], self._order_wp,
                                                    self.n_particles], outputs=[seed], device=self.device)

    def _keep_positions(self, state: _State, positions: wp.array, frame: int) -> None:
        """Copy ``state``'s positions, in the callers' order, into ``frame``'s of ``positions``."""
        n = self.n_batch * self.n_particles
        if self._order is None:
            wp.copy(positions, state.x, dest_offset=frame * n, count=n)
        else:
            wp.launch(_to_callers, dim=n, inputs=[state.x, self._order_wp, self.n_particles],
                      outputs=[positions[frame * n:(frame + 1) * n]], device=self.device)

    def last_state(self) -> SimState:
        """The particle state at the end of the last rollout."""
        if self._final is None:
            raise RuntimeError("last_state() needs a preceding rollout()")
        return self._sim_state(self._final)

    def frame_state(self, frame: int) -> SimState:
        """The state at ``frame`` of the last ``grad=True`` rollout (from its checkpoints)."""
        if self._record is None:
            raise RuntimeError("frame_state() needs a preceding rollout(..., grad=True)")
        return self._sim_state(self._record["checkpoints"][frame])

    def _sim_state(self, state: _State) -> SimState:
        B, N = self.n_batch, self.n_particles
        x, v, C, b = (self._outward(self._staging.download(a, np.float64).reshape(B, N, *a.dtype._shape_))
                      for a in state.arrays)
        return SimState(x, v, C, b)

    @property
    def own_steps_allowed(self) -> bool:
        """Whether ``rollout(own_steps=True)`` may step each batch row at its own time step.

        Not with colliders: their poses are the frame's, one per substep of one time step. An
        effect's hooks need no step of their own: a row whose frame is done puts no mass on its
        grid, where an acceleration then moves nothing, and its particles' stresses are not read.
        """
        return not self.config.colliders

    def rollout(self, n_frames: int, *, grad: bool = False, check: bool = True,
                substeps: int | None = None, initial: SimState | None = None,
                start_frame: int = 0, progress=None, own_steps: bool = False) -> np.ndarray:
        """Advance ``n_frames`` frames; positions (n_frames + 1, B, N, 3), frame 0 the start.

        ``grad=True`` keeps per-frame checkpoints for ``backward``. ``substeps`` forces the
        substeps per frame (see ``time_step``). ``initial`` starts from a given state (e.g. the
        ``last_state()`` of an earlier rollout, or positions resynchronised to observations);
        by default the rollout starts at rest deformation from the particles and ``v0``.
        ``start_frame`` is the frame the rollout starts at on the scene's clock (colliders move
        along their trajectories from there). ``progress(frame)`` is called after each frame.

        ``own_steps=True`` steps each batch row at its own time step (``own_time_steps``) instead
        of every row at the stiffest one's: a row's frame is its own substeps, after which it
        waits for the others (its kernels copy its state). Each row moves as a simulator of it
        alone would (on the CPU to the bit), in the time the stiffest row takes, with the work of
        the rows that are still stepping; with ``grad``, ``backward`` gives each row the
        gradients that row alone would have. Not with ``substeps``, and only where
        ``own_steps_allowed``.
        """
        self._queue_rollout(n_frames, grad, check, substeps, initial, start_frame, progress, own_steps,
                            download=True).wait()
        return self._staging.collect().reshape(n_frames + 1, self.n_batch, self.n_particles, 3)

    def queue_rollout(self, n_frames: int, *, grad: bool = False, check: bool = True,
                      substeps: int | None = None, initial: SimState | None = None,
                      start_frame: int = 0, own_steps: bool = False) -> QueuedRollout:
        """``rollout``, queued: its positions stay on the device, and nothing waits for them here.

        On a GPU the host goes on while the device computes, so that a caller can queue what
        reads the positions (the fit's loss, ``identify.fit``) behind the rollout before waiting
        for it (``QueuedRollout.wait``); a frame's check is read there, not here. On the CPU the
        rollout has run when this returns, and it stops at the frame that diverged.
        """
        return self._queue_rollout(n_frames, grad, check, substeps, initial, start_frame, None, own_steps,
                                   download=False)

    def _queue_rollout(self, n_frames: int, grad: bool, check: bool, substeps: int | None,
                       initial: SimState | None, start_frame: int, progress, own_steps: bool,
                       download: bool) -> QueuedRollout:
        """``queue_rollout``; ``download``: the positions are copied to the host as they come (``_staging``)."""
        if own_steps:
            if substeps is not None:
                raise ValueError("own_steps=True takes no substeps")
            if not self.own_steps_allowed:
                raise ParameterError("rows at their own time steps need a scene without colliders")
            row_substeps, dt = self.own_time_steps()
            n_sub = int(row_substeps.max())
        else:
            n_sub, dt = self.time_step(substeps)
            row_substeps = n_sub
        self._set_steps(dt, row_substeps)
        B, N = self.n_batch, self.n_particles
        self._record = None  # a rollout that stops diverging leaves none (kept frames are rewritten)
        if self._buffers is None:
            self._buffers = ([_State(B * N, self.device, False) for _ in range(2)],
                             _Grid(B, self.n_objects, self.dims, B * N, self._stress,
                                   self.device, False, self._accelerated,
                                   clears=self.device != "cpu" and self.n_objects * self.n_nodes
                                   > CLEAR_NODES * self.n_particles))
        states, grid = self._buffers
        if grid.clears:  # cleared whole here, outside the captured graphs: a rollout before may have diverged
            grid.clear()
        if initial is None:
            self._initial_state(states[0])
        else:
            self._assign_state(states[0], initial)
        # Positions and checks of every frame stay on the device until the end, so that on a GPU
        # the frames are queued without waiting for the host; the CPU (synchronous anyway), and
        # a caller who follows the progress, read each frame's check at once and stop there.
        positions = wp.empty((n_frames + 1) * B * N, dtype=wp.vec3, device=self.device)
        row = 4 * B * self.n_objects
        stats = wp.array(np.tile(np.float32([0.0, 0.0, 0.0, np.inf]), n_frames * B * self.n_objects),
                         dtype=float, device=self.device)
        early = self.device == "cpu" or progress is not None
        self._keep_positions(states[0], positions, 0)
        if download:
            self._staging.stage(positions)
        kept = self._kept_frames(n_frames, n_sub) if grad else None
        checkpoints = [] if kept or not grad else [_clone(states[0])]
        state, current = states[0], 0
        work = self._tape_buffers_for(n_sub)[0] if kept else None
        for frame in range(n_frames):
            if kept:  # recorded on a tape, whose states and grids are kept for ``backward``
                self._pose_colliders(work.colliders, start_frame + frame, n_sub, dt)
                work.states[0].copy_from(states[0] if frame == 0 else work.states[n_sub])
                self._record_frame(work, n_sub)
                wp.copy(kept[frame], work.values, count=work.words(n_sub))
                start, state = self._kept_states(kept[frame], work, n_sub)
                if frame == 0:
                    checkpoints.append(start)
            else:
                if not own_steps:  # rows at their own steps have no colliders
                    self._collider_poses(start_frame + frame, n_sub, dt)
                current = self._frame(states, current, grid, n_sub)
                state = states[current]
            if check:
                frame_stats = stats[frame * row:(frame + 1) * row]
                self._check(state, frame_stats)
                if early:
                    self._diverged(frame_stats.numpy(), start_frame + frame + 1, dt)
            self._keep_positions(state, positions, frame + 1)
            if download:
                self._staging.part((frame + 2) * B * N)  # copied to the host while the next frame runs
            if grad:
                checkpoints.append(state if kept else _clone(state))
            if progress is not None:
                progress(frame + 1)
        record = ({"checkpoints": checkpoints, "n_sub": n_sub, "dt": dt, "substeps": row_substeps,
                   "start_frame": start_frame, "kept": kept} if grad else None)
        self._queued += 1
        token = self._queued

        def wait() -> None:
            if token != self._queued:
                raise RuntimeError("a queued rollout was waited for after the simulator's next rollout")
            if check and not early:
                self._diverged(stats.numpy(), start_frame + 1, dt)
            self._record, self._final = record, state
            _LOG.debug("rollout: %d frames x %d substeps (dt %.3g s), %d particles x %d batches",
                       n_frames, n_sub, np.min(dt), N, B)

        return QueuedRollout(positions, wait)

    def backward(self, dL_dx: np.ndarray | wp.array) -> Gradients:
        """Gradients of a loss L given dL/dx at every frame of the last ``grad=True`` rollout.

        ``dL_dx`` is (F + 1, B, N, 3) like the positions ``rollout`` returned, or ((F + 1) B N,)
        ``wp.vec3`` on the simulator's device like ``QueuedRollout.positions``, read there after
        the work queued on the simulator's stream so far (nothing then waits for the host).
        """
        if self._record is None:
            raise RuntimeError("backward() needs a preceding rollout(..., grad=True)")
        if self._p2g is kernels.p2g:  # its written adjoint, built by the first backward (4.4 s on an empty cache, H200)
            load_modules(self.device, [self._written[kernels.p2g][0].module.name])
        checkpoints, n_sub, dt, substeps, start = (
            self._record[k] for k in ("checkpoints", "n_sub", "dt", "substeps", "start_frame"))
        n_frames = len(checkpoints) - 1
        B, N = self.n_batch, self.n_particles
        on_device = isinstance(dL_dx, wp.array)
        if on_device:
            size = (n_frames + 1) * B * N
            if dL_dx.dtype != wp.vec3 or dL_dx.shape != (size,) or dL_dx.device != wp.get_device(self.device):
                raise ValueError(f"dL_dx on the device must be {size} wp.vec3 on {self.device}, "
                                 f"not {dL_dx.shape} {wp.types.type_repr(dL_dx.dtype)} on {dL_dx.device}")
        else:
            dL_dx = np.asarray(dL_dx, dtype=np.float32)
            if dL_dx.shape != (n_frames + 1, B, N, 3):
                raise ValueError(f"dL_dx has shape {dL_dx.shape}, expected {(n_frames + 1, B, N, 3)}")
        adjoint, seed = self._adjoint_state()
        self._set_steps(dt, substeps)
        self.params.zero_grad()
        self.volume.grad.zero_()
        for array in adjoint.arrays:
            array.zero_()

        if on_device:
            def seeded(index: int) -> None:
                self._seed_from(dL_dx, index + 1, seed)
        else:
            # each frame's dL/dx staged apart, so that the host stages the next while the device
            # runs this frame's adjoint
            self._staging.reserve(wp.vec3, n_frames * B * N)

            def seeded(index: int) -> None:
                self._staging.put(self._inward(dL_dx[index + 1]).reshape(-1, 3), wp.vec3, seed, index * B * N)

        frames = self._tape_buffers_for(n_sub)

        def prepare(index: int) -> _FrameTape:  # the host's part: frame ``index`` at its start
            frame = frames[index % len(frames)]
            if kept:
                wp.copy(frame.values, kept[index], count=frame.words(n_sub))
            else:
                frame.states[0].copy_from(checkpoints[index])
            self._pose_colliders(frame.colliders, start + index, n_sub, dt)
            return frame

        kept, self._record["kept"] = self._record["kept"], None  # a second backward recomputes
        if kept:  # a frame's states and grids back in place, its adjoint
            frame = frames[0]
            for index in reversed(range(n_frames)):
                prepare(index)
                seeded(index)
                self._kept_adjoint(frame, n_sub, adjoint, seed)
            return self._gradients(adjoint)

        if len(frames) == 1:  # a CUDA device: a frame's recomputation, then its adjoint
            frame = frames[0]
            for index in reversed(range(n_frames)):
                prepare(index)
                seeded(index)
                self._recomputed_adjoint(frame, n_sub, adjoint, seed)
        else:  # the CPU: a second thread recomputes the frame before while this one's adjoint runs
            def recorded(index: int) -> _FrameTape:
                frame = prepare(index)
                self._zero_frame_grad(frame)
                self._record_frame(frame, n_sub)
                return frame

            with ThreadPoolExecutor(1) as ahead, ThreadPoolExecutor(ADJOINT_PARTS - 1) as helper:
                pending = ahead.submit(recorded, n_frames - 1)
                for index in reversed(range(n_frames)):
                    frame = pending.result()
                    if index > 0:
                        pending = ahead.submit(recorded, index - 1)
                    seeded(index)
                    self._frame_adjoint(frame, n_sub, adjoint, seed, helper)
        return self._gradients(adjoint)

    def _gradients(self, adjoint: _State) -> Gradients:
        """What ``backward`` returns, once ``adjoint`` holds dL/d(state) at the first frame."""
        B, N = self.n_batch, self.n_particles
        # x0 and v0 enter through _init_state; v0's adjoint is the frame-0 velocity adjoint.
        return Gradients(
            params=self.params.grads(),
            v0=self._outward(self._staging.download(adjoint.v, np.float64).reshape(B, N, 3)),
            volume=self._outward(self._staging.download(self.volume.grad, np.float64).reshape(B, N)),
        )

    def _frame_tape(self, capacity: int) -> _FrameTape:
        """New buffers to record a frame of up to ``capacity`` substeps on."""
        B, total, d = self.n_batch, self.n_batch * self.n_particles, self.device
        state_bytes = _Arena.offsets(_State.specs(total))[-1]
        grid_bytes = _Arena.offsets(_Grid.specs(B, self.n_objects, self.dims, total, self._stress,
                                                self._accelerated, True, False,
                                                vector_reductions(self.device)))[-1]
        # the arenas' sizes are multiples of ALIGN: in the frame's arenas they lie back to back
        state, grid = _Arena.raw(state_bytes), _Arena.raw(grid_bytes)
        specs = [state, grid] * capacity + [state]
        values, grads = _Arena(specs, d), _Arena(specs, d)
        memory = list(zip(values.arrays, grads.arrays, strict=True))
        return _FrameTape([_State(total, d, True, m) for m in memory[0::2]],
                          [_Grid(B, self.n_objects, self.dims, total, self._stress, d, True, self._accelerated, m)
                           for m in memory[1::2]],
                          self._collider_arrays(capacity), values.memory, grads.memory, state_bytes, grid_bytes)

    def _tape_buffers_for(self, n_sub: int) -> list[_FrameTape]:
        """Buffers of a frame recomputed on a tape (two on the CPU, ``backward`` says why).

        On a GPU they have room for ``SUBSTEP_HEADROOM`` more substeps than the first frame
        asked for: a fit's substeps change with its stiffness from one iteration to the next,
        and new buffers would drop every captured graph.
        """
        if self._tape_buffers is None or len(self._tape_buffers[0].grids) < n_sub:
            self._tape_buffers = None  # free the old buffers before allocating the new ones
            self._forget_graphs("kept", "adjoint")
            self._tape_buffers = [self._frame_tape(self._capacity(n_sub))
                                  for _ in range(2 if self.device == "cpu" else 1)]
        return self._tape_buffers

    def _capacity(self, n_sub: int) -> int:
        """The substeps that new frame buffers or collider poses have room for (``_tape_buffers_for``)."""
        return n_sub if self.device == "cpu" else math.ceil(n_sub * SUBSTEP_HEADROOM)

    def _adjoint_state(self) -> tuple[_State, wp.array]:
        """The adjoint state that ``backward`` carries back, and the buffer of a frame's dL/dx."""
        if self._adjoint_buffers is None:
            total = self.n_batch * self.n_particles
            self._adjoint_buffers = (_State(total, self.device, False),
                                     wp.zeros(total, dtype=wp.vec3, device=self.device))
        return self._adjoint_buffers

    def _kept_frames(self, n_frames: int, n_sub: int) -> list[wp.array] | None:
        """Where each of ``n_frames`` frames' values go (``_FrameTape.values``), if they fit.

        On a CUDA device, within ``SimConfig.tape_memory``; else None, and the kept blocks are
        freed. Blocks are kept for later rollouts of as many frames or fewer.
        """
        budget = self.config.tape_memory
        if budget is None and self.device != "cpu":  # what the kept blocks hold counts as free
            card = wp.get_device(self.device)
            free = card.free_memory + sum(block.capacity for block in self._kept)
            budget = min(card.total_memory / 3, free / 2) / 1e9
        size = self._tape_buffers_for(n_sub)[0].values.size if self.device != "cpu" and budget > 0 else 0
        if not size or n_frames * size * _Arena.ALIGN > budget * 1e9:
            self._kept = []
            return None
        if self._kept and self._kept[0].shape[0] != size:
            self._kept = []
        while len(self._kept) < n_frames:
            self._kept.append(wp.empty(size, dtype=_Arena.WORD, device=self.device))
        return self._kept[:n_frames]

    def _kept_states(self, block: wp.array, frame: _FrameTape, n_sub: int) -> tuple[_State, _State]:
        """The first and the last state of a frame of ``n_sub`` substeps kept in ``block``."""
        total = self.n_batch * self.n_particles
        views = _Arena([_Arena.raw(frame.prefix(n_sub) - frame.state_bytes), _Arena.raw(frame.state_bytes)],
                       self.device, block).arrays
        return (_State(total, self.device, False, (views[0], None)),
                _State(total, self.device, False, (views[1], None)))

    def _recomputed_adjoint(self, frame: _FrameTape, n_sub: int, adjoint: _State, seed: wp.array) -> None:
        """A frame recomputed from ``frame.states[0]`` on tapes, then its adjoint (a GPU's backward)."""
        self._zero_frame_grad(frame)
        self._record_frame(frame, n_sub)
        self._frame_adjoint(frame, n_sub, adjoint, seed)

    def _kept_adjoint(self, frame: _FrameTape, n_sub: int, adjoint: _State, seed: wp.array) -> None:
        """The adjoint of a frame whose values ``backward`` put back on ``frame``."""
        self._zero_frame_grad(frame)
        self._frame_adjoint(frame, n_sub, adjoint, seed)


def _clone(state: _State) -> _State:
    copy = _State(state.x.shape[0], state.x.device, False)
    copy.copy_from(state)
    return copy
