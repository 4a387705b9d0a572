"""Per-object material identification by differentiable MPM rollouts (MOSIV stage 3).

``Identifier(problem, settings).run()`` fits the free parameters of a ``FitProblem`` (per-object
material parameters, ground and effect parameters, and each object's initial linear and angular
velocity) to its observations with Adam on the simulator's gradients:

- coordinates: each parameter moves in ``identify.coordinates`` (log for moduli, bounded logits
  for nu and friction), velocities in m/s and rad/s; Adam's steps are projected back into each
  coordinate's range, whose top for E and the bulk modulus is ``max_modulus`` (1 MPa): along a
  direction the data leave flat a modulus would otherwise climb on, and each iteration's cost
  with it (the time step shrinks as 1 / sqrt(modulus));
- initial velocities start from the observed centroid motion of the first frames (an object
  found at rest keeps a zero initial velocity; the others' are refined with the parameters);
- before Adam, a gradient-free search, all its candidates simulated in batched rollouts of
  the first ``search_frames`` frames (0 = all): ``search_samples`` points of a Latin hypercube
  over a box, which for a material parameter is its prior range ``SEARCH_RANGES`` (a yield
  stress far above the true one leaves the loss flat, so no gradient finds the way down: the
  samples must land below it) and otherwise the initial value +- ``search_decades`` decades
  (scale parameters) or 2 logit units. Samples are scored by the objective Adam minimises
  (Chamfer and silhouette terms). The best sample is kept; with per-object losses, so is
  the composite that takes each object's parameters from the sample that fits that object
  best (each object's loss depends mostly on its own parameters, so 32 samples search each
  object's few dimensions rather than all objects' together), whichever of the two fits
  better. The ``search_starts`` best points of this first round are the starts: each then
  goes through ``search_rounds`` more such rounds, each in a box 3x narrower than the last
  around its best so far (samples that move every coordinate at once follow the valleys of
  coupled parameters, such as E and nu, which one-coordinate-at-a-time passes stall in), and
  the lowest end wins. Several starts keep other basins alive: coupled parameters can explain
  the same motion twice (on elastic_on_plastic one start narrowed onto a clay yield stress of
  456 Pa with a ground friction of 1.9, at a higher loss than the true 800 Pa and 0.5), and
  the first round's best need not lie in the basin of lowest loss;
- horizon curriculum (M-PhyGs temporal mini-batches, MOSIV horizon curriculum): stage h fits
  windows of h frames, up to ``windows`` of them spread over the sequence and taken in turn;
  the last stage (0) fits the whole sequence from frame 0;
- resynchronisation (MOSIV): a window that starts at frame s > 0 starts from the state of an
  anchor rollout with the current parameters at s, each object's particles shifted (and their
  velocities offset) so that its centroid position and velocity match the observations at s,
  which stops drift from one window leaking into the next. The anchor is refreshed every
  ``resync_every`` iterations;
- the result is the lowest whole-window loss among the search's point, the whole-sequence
  stage's iterates and Adam's last step (a windowed stage's objective is not the whole window's,
  and Adam's last step need not be its best);
- a diverging rollout (a window's or the anchor's) does not end the fit: the step is undone
  and the learning rate halved; a last step that diverges loses to the other points;
- with a checkpoint directory the state is written after every iteration and a rerun of the
  same problem resumes from it.

What it is for: the fit. What it is not for: choosing a family (``identify.family``),
uncertainty (``identify.uncertainty``), or reading bags and nodes.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import math
import os
import queue
import time
import zipfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, fields, replace
from functools import partial
from pathlib import Path

import numpy as np

from mosiv_ros.config import FitConfig
from mosiv_ros.identify.coordinates import Coordinate
from mosiv_ros.identify.losses import geometry_loss, silhouette_losses, silhouette_object_losses
from mosiv_ros.identify.observations import Observations
from mosiv_ros.io.files import replacing
from mosiv_ros.lifting.lift import boundary_volume
from mosiv_ros.sim import ObjectModel, Particles, SimConfig, SimState, Simulator
from mosiv_ros.sim.errors import SimulationDiverged, SimulationError
from mosiv_ros.sim.materials import FAMILY_PARAMS, MATERIAL_PARAM_NAMES
from mosiv_ros.simulation import OFFSET

_LOG = logging.getLogger(__name__)

CHECKPOINT_FILE = "identify_checkpoint.npz"

SEARCH_RANGES = {
    "E": (3.0e3, 1.0e6),
    "nu": (0.05, 0.45),
    "yield_stress": (1.0e2, 3.0e4),
    "friction_angle": (math.radians(15.0), math.radians(50.0)),
    "bulk_modulus": (1.0e4, 1.0e6),
    "viscosity": (1.0e-2, 1.0e2),
    "friction": (0.05, 1.5),
}
"""Prior ranges (SI) of the material parameters that the global search samples: soft solids,
clays, sands and liquids a robot handles. Adam may leave them, the moduli only up to
``FitSettings.max_modulus``."""

MODULI = ("E", "bulk_modulus")
"""Parameters that set the stable time step through the wave speed: ``max_modulus`` caps them."""


@dataclass
class FitSettings(FitConfig):
    """How a fit runs: identify_node's fit parameters (``config.FitConfig``) and internal settings.

    The parameters' defaults and meaning are in ``config``; no parameter sets the ones below.
    """

    fit_velocity: bool = True
    resync_every: int = 10
    splat_radius: float = 0.005
    search_decades: float = 1.0

    @classmethod
    def of(cls, config: FitConfig) -> FitSettings:
        """The settings of a fit that identify_node's parameters ``config`` ask for."""
        return cls(**{f.name: copy.deepcopy(getattr(config, f.name)) for f in fields(FitConfig)})

    def result_settings(self) -> dict:
        """The settings a fit's result depends on: all but where it checkpoints and how many cores."""
        return asdict(replace(self, checkpoint_dir="", cpu_workers=0))


@dataclass
class FitProblem:
    """What to fit: a scene's objects, particles at the first observed frame, observations.

    ``free`` names the parameters to fit: a per-object material parameter name applies to every
    object whose family uses it, except where ``fixed[object name]`` lists it (a declared, known
    value); a per-object effect parameter (``drag.coefficient``) applies to every object not
    ``fixed`` for it; other names (``ground.friction``) are fitted as they are, a vector as all
    its components or one (``wind.a[1]``). Every other parameter keeps its value in the
    simulator.
    """

    objects: list[ObjectModel]
    particles: Particles
    observations: Observations
    sim_config: SimConfig
    free: list[str]
    fixed: dict[str, set[str]] = field(default_factory=dict)
    boundary: Boundary | None = None
    initial_velocity: np.ndarray | None = None
    """(K, 3) m/s: where known better than the first frames' centroids tell (NaN rows: not)."""
    warm_start: tuple[np.ndarray, np.ndarray] | None = None
    """(u, velocity) where an earlier fit of this same problem ended: start there, no search."""


@dataclass
class Boundary:
    """M-PhyGs boundary particles (Sec. A, Eq. 1): V_i = V_g (sigmoid(-beta (d_i + o_k)) + eps).

    ``sdf`` (N,) signed distance of each particle to the estimated surface (m, negative inside),
    ``lattice_volume`` V_g, ``band`` the half-width of the band (the offsets' range +-band).
    A per-object offset o_k is fitted with the other parameters; particles outside the moved
    boundary (V_i < V_g / 2) carry almost no mass and take no part in the geometry loss.
    """

    sdf: np.ndarray
    lattice_volume: float
    beta: float
    eps: float
    band: float

    def volumes(self, offsets_per_particle: np.ndarray) -> np.ndarray:
        return boundary_volume(self.sdf, self.lattice_volume, offsets_per_particle, self.beta, self.eps)

    def dvolume_doffset(self, offsets_per_particle: np.ndarray) -> np.ndarray:
        sig = 0.5 * (1.0 + np.tanh(-0.5 * self.beta * (self.sdf + offsets_per_particle)))
        return -self.beta * self.lattice_volume * sig * (1.0 - sig)

    def inside(self, offsets_per_particle: np.ndarray) -> np.ndarray:
        return self.sdf + offsets_per_particle <= 0.0


@dataclass
class Entry:
    """One free scalar: parameter ``name`` at ``index`` in its (batch, ...) array.

    A boundary offset has ``name`` ``OFFSET`` and index (0, object index).
    """

    name: str
    index: tuple[int, ...]
    coordinate: Coordinate
    label: str
    per_object: bool = False


@dataclass
class FitResult:
    """What a fit found.

    Fitted values by parameter name (shaped like ``Parameters.get`` without the batch), the
    free entries and their coordinates, initial velocities per object, the loss history (each
    iteration with its wall time split into simulation forward, loss and backward), the wall time
    of the search.
    """

    values: dict[str, np.ndarray]
    entries: list[Entry]
    u: np.ndarray
    velocity: np.ndarray  # (K, 6): linear m/s, angular rad/s
    loss: float
    per_object_loss: np.ndarray
    history: list[dict] = field(default_factory=list)
    failures: int = 0
    search_s: float = 0.0


class Identifier:
    """Fits a ``FitProblem``; see the module docstring."""

    def __init__(self, problem: FitProblem, settings: FitSettings | None = None,
                 progress: Callable[[dict], None] | None = None) -> None:
        self.problem = problem
        self.settings = settings or FitSettings()
        self.progress = progress
        obs = problem.observations
        if obs.n_objects != len(problem.objects):
            raise ValueError(f"observations cover {obs.n_objects} objects, the problem has "
                             f"{len(problem.objects)}")
        if obs.n_frames < 2:
            raise ValueError(f"need at least 2 observed frames, got {obs.n_frames}")
        if self.settings.cpu_workers < 0:
            raise ValueError(f"cpu_workers must be 0 (every core) or more, got {self.settings.cpu_workers}")
        if abs(obs.frame_dt - problem.sim_config.frame_dt) > 1e-9:
            raise ValueError(f"observation frame_dt {obs.frame_dt} differs from the simulator's "
                             f"{problem.sim_config.frame_dt}")
        self.sim = Simulator(problem.objects, problem.particles, problem.sim_config)
        self.offsets = np.zeros(len(problem.objects))
        self.inside = np.ones(len(problem.particles.x), dtype=bool)
        self.entries = self._entries(problem.free)
        self.index = problem.particles.object_index
        self.centre0 = np.stack([problem.particles.x[self.index == k].mean(axis=0)
                                 for k in range(len(problem.objects))])
        self.observed_centroids = obs.centroids()
        self._batches: dict[tuple[int, int], Simulator] = {}
        self.timing: dict[str, float] = {}  # of the last window: forward_s, loss_s, backward_s
        self.start: tuple[np.ndarray, np.ndarray] = (np.zeros(0), np.zeros(0))  # Adam's start
        # the lowest whole-window loss an iteration saw: (loss, u, velocity, per-object losses)
        self.best: tuple[float, np.ndarray, np.ndarray, np.ndarray] = (
            math.inf, np.zeros(0), np.zeros(0), np.zeros(0))
        self.torch_device = self.sim.device if self.sim.device.startswith("cuda") else "cpu"

    def report(self, record: dict) -> None:
        """Hand a progress record to the ``progress`` callback, if any.

        Every record has ``phase`` ("search": samples scored; "fit": Adam iterations, with the
        iteration's history entry; "uncertainty": rollouts of the curvature), ``done`` and
        ``total`` (the phase's units, counted over the whole fit).
        """
        if self.progress is not None:
            self.progress(record)

    # --- parameters <-> optimisation vector --------------------------------------------------

    def _entries(self, free: list[str]) -> list[Entry]:
        entries = []
        params = self.sim.params
        for free_name in free:
            name, component = _component(free_name)
            spec = params.spec(name)
            coordinate = Coordinate.for_spec(spec)
            if name in MODULI:
                if not self.settings.max_modulus > coordinate.lower:
                    raise ValueError(f"max_modulus must exceed {name}'s lower bound {coordinate.lower:g} "
                                     f"Pa, got {self.settings.max_modulus:g}")
                coordinate = replace(coordinate, upper=min(coordinate.upper, self.settings.max_modulus))
            if spec.per_object:
                for k, obj in enumerate(self.problem.objects):
                    uses = name in FAMILY_PARAMS[obj.family] or name not in MATERIAL_PARAM_NAMES
                    if uses and name not in self.problem.fixed.get(obj.name, ()):
                        entries.append(Entry(name, (0, k), coordinate, f"{obj.name}.{name}", True))
            elif spec.size > 1:
                components = range(spec.size) if component is None else [component]
                entries += [Entry(name, (0, c), coordinate, f"{name}[{c}]") for c in components]
            else:
                entries.append(Entry(name, (0,), coordinate, name))
        boundary = self.problem.boundary
        if boundary is not None and boundary.band > 0:
            coordinate = Coordinate("logit", -boundary.band, boundary.band)
            entries += [Entry(OFFSET, (0, k), coordinate, f"{obj.name}.{OFFSET}", True)
                        for k, obj in enumerate(self.problem.objects)]
        if not entries:
            raise ValueError(f"nothing to fit: none of {free} applies to these objects")
        return entries

    def start_from(self, offsets: np.ndarray, velocity: np.ndarray) -> None:
        """Set ``sim`` up to roll out, unfitted, from the parameters it holds.

        With these boundary offsets (K,) and initial velocities (K, 6: linear m/s, angular rad/s
        about each centroid); for a caller that rolls ``sim`` out without fitting (the loop
        closure's probes).
        """
        self.offsets[:] = offsets
        self._apply(self._pack(), velocity)

    def _pack(self) -> np.ndarray:
        u = [e.coordinate.to_u(self.offsets[e.index[1]] if e.name == OFFSET
                               else self.sim.params.get(e.name)[e.index]) for e in self.entries]
        return np.asarray(u, dtype=np.float64)

    def _apply(self, u: np.ndarray, velocity: np.ndarray) -> None:
        for entry, value in zip(self.entries, u, strict=True):
            if entry.name == OFFSET:
                self.offsets[entry.index[1]] = entry.coordinate.to_theta(value)
                continue
            current = self.sim.params.get(entry.name)
            current[entry.index] = entry.coordinate.to_theta(value)
            self.sim.params.set(entry.name, current)
        boundary = self.problem.boundary
        if boundary is not None:
            self.sim.set_volume(boundary.volumes(self.offsets[self.index]))
            self.inside = boundary.inside(self.offsets[self.index])
        linear, angular = velocity[self.index, :3], velocity[self.index, 3:]
        self.sim.set_initial_velocity(linear + np.cross(angular, self.problem.particles.x
                                                        - self.centre0[self.index]))

    # --- one window --------------------------------------------------------------------------

    def _window_loss(self, start: int, length: int, initial: SimState | None,
                     grad: bool) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Loss over frames start+1..start+length, dL/du, dL/dvelocity (K, 6), per-object losses."""
        obs, s = self.problem.observations, self.settings
        tick = time.perf_counter()
        traj = self.sim.rollout(length, grad=grad, initial=initial, start_frame=start)
        self.timing = {"forward_s": time.perf_counter() - tick}
        tick = time.perf_counter()
        dL = np.zeros(traj.shape, dtype=np.float64)
        total, per = 0.0, np.zeros(obs.n_objects)
        inside = self.inside
        for f in range(1, length + 1):
            x = traj[f, 0].astype(np.float64)
            value, g, per_f = geometry_loss(x[inside], self.index[inside], obs.points[start + f],
                                            s.per_object_loss, obs.trees(start + f))
            total += s.chamfer_weight * value
            dL[f, 0, inside] = s.chamfer_weight * g
            per += np.nan_to_num(per_f)
        if s.silhouette_weight > 0 and obs.masks:
            # the particles the Chamfer scores, not the boundary band outside the surface
            value, g = silhouette_losses(traj[1:, 0][:, inside], self.index[inside], obs.object_ids,
                                         obs.views, obs.masks[start + 1: start + length + 1],
                                         s.splat_radius, s.per_object_loss, self.torch_device)
            total += s.silhouette_weight * value
            dL[1:, 0, inside] += s.silhouette_weight * g
        total, dL, per = total / length, dL / length, per / length
        self.timing["loss_s"] = time.perf_counter() - tick
        if not grad:
            return total, np.zeros(len(self.entries)), np.zeros((obs.n_objects, 6)), per
        tick = time.perf_counter()
        grads = self.sim.backward(dL)
        self.timing["backward_s"] = time.perf_counter() - tick
        u = self._pack()
        boundary = self.problem.boundary
        if boundary is not None:
            dL_do = grads.volume[0] * boundary.dvolume_doffset(self.offsets[self.index])
            offset_grads = np.bincount(self.index, dL_do, minlength=obs.n_objects)
        du = np.array([(offset_grads[e.index[1]] if e.name == OFFSET else grads.params[e.name][e.index])
                       * e.coordinate.dtheta_du(u[i]) for i, e in enumerate(self.entries)])
        dv = np.zeros((obs.n_objects, 6))
        if initial is None:  # velocities are parameters only of windows from frame 0
            g0 = grads.v0[0]
            r = self.problem.particles.x - self.centre0[self.index]
            for k in range(obs.n_objects):
                mine = self.index == k
                dv[k, :3] = g0[mine].sum(axis=0)
                dv[k, 3:] = np.cross(r[mine], g0[mine]).sum(axis=0)
        return total, du, dv, per

    def _resynced(self, anchor: dict[int, SimState], start: int) -> SimState:
        """The anchor state at ``start`` with each object's centroid moved onto the observed one."""
        state = anchor[start]
        x, v = state.x.copy(), state.v.copy()
        c_obs = self.observed_centroids
        dt = self.problem.observations.frame_dt
        for k in range(self.problem.observations.n_objects):
            mine = self.index == k
            if np.isnan(c_obs[start, k, 0]):
                continue
            x[0, mine] += c_obs[start, k] - x[0, mine].mean(axis=0)
            # central difference: a forward one lags by half a frame of acceleration
            before, after = c_obs[start - 1, k], c_obs[min(start + 1, len(c_obs) - 1), k]
            if start + 1 < len(c_obs) and not (np.isnan(before[0]) or np.isnan(after[0])):
                v[0, mine] += (after - before) / (2 * dt) - v[0, mine].mean(axis=0)
        return SimState(x, v, state.C, state.b)

    def _anchor(self, starts: list[int]) -> dict[int, SimState]:
        last = max(starts)
        if last == 0:
            return {}
        self.sim.rollout(last, grad=True)
        return {s: self.sim.frame_state(s) for s in starts if s > 0}

    # --- gradient-free initialisation -------------------------------------------------------

    def batch_losses(self, candidates: np.ndarray, velocity: np.ndarray,
                     frames: int | None = None, together: bool | None = None) -> np.ndarray:
        """The fit's loss of each row of ``candidates`` (coordinate vectors, (B, P)).

        The same objective as Adam's (weighted Chamfer and silhouette terms, mean over frames),
        without gradients.

        ``together`` (default: on a GPU): every row at the time step of the stiffest row, in one
        batched rollout; else each row at its own stable time step (on the CPU a batch costs as
        much as its rows, and the loss of one parameter set differs by up to 10 % between time
        steps). On the CPU the rows, or slices of them when together, are simulated side by side,
        one simulator per core (``FitSettings.cpu_workers``). Over frames 1..``frames`` (default
        all); NaN where a rollout diverged (every row of its batch or slice).
        """
        return self.batch_object_losses(candidates, velocity, frames, together)[0]

    def batch_object_losses(self, candidates: np.ndarray, velocity: np.ndarray,
                            frames: int | None = None,
                            together: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``batch_losses`` and each object's share of them, (B,) and (B, K).

        The shares are NaN with the scene-level (ablation) loss, which does not split by object.
        """
        obs = self.problem.observations
        frames = min(frames or obs.n_frames - 1, obs.n_frames - 1)
        cuda = self.sim.device.startswith("cuda")
        if together is None:
            together = cuda
        self._apply(candidates[0], velocity)  # the rows' common set-up: initial velocity, fixed values
        for f in range(1, frames + 1):
            obs.trees(f)  # built once, before threads share them
        # On the CPU each simulator runs on one core and its kernels release the GIL, so rows (or
        # slices of a batch) run side by side on every core, with the same results as in turn.
        workers = 1 if cuda else max(1, min(len(candidates), self.settings.cpu_workers or os.cpu_count() or 1))
        if together:  # one time step, the stiffest row's, for every row
            groups = [candidates] if cuda else np.array_split(candidates, workers)
            sims = [self._batch(len(g), slot) for slot, g in enumerate(groups)]
            insides = [self._configure(sim, g) for sim, g in zip(sims, groups, strict=True)]
            substeps = max(sim.time_step()[0] for sim in sims)
            jobs = [partial(self._score, sim, inside, frames, substeps)
                    for sim, inside in zip(sims, insides, strict=True)]
        else:  # each row at its own time step, on the simulator of a free slot
            idle = queue.SimpleQueue()
            for slot in range(workers):
                idle.put(self._batch(1, slot))

            def one(row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                sim = idle.get()
                try:
                    return self._score(sim, self._configure(sim, row[None]), frames)
                finally:
                    idle.put(sim)

            jobs = [partial(one, row) for row in candidates]
        if workers == 1:  # the GPU's one batch, or one core: in this thread, as before the threads
            results = [job() for job in jobs]
        else:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                results = list(pool.map(lambda job: job(), jobs))
        return (np.concatenate([total for total, _ in results]),
                np.concatenate([per for _, per in results]))

    def _batch(self, n: int, slot: int = 0) -> Simulator:
        """The kept simulator of ``n`` batched rows for worker ``slot`` (made on first use)."""
        key = (n, slot)
        if key not in self._batches:
            self._batches[key] = Simulator(self.problem.objects, self.problem.particles,
                                           self.problem.sim_config, n_batch=n)
        return self._batches[key]

    def _configure(self, batch: Simulator, candidates: np.ndarray) -> np.ndarray:
        """Set ``batch`` to the rows ``candidates``; (B, N) which particles are inside the surface.

        What no entry sets comes from the fit's own simulator, as ``_apply`` left it.
        """
        n = len(candidates)
        batch.set_initial_velocity(self.sim.v0.numpy()[: self.sim.n_particles])
        offsets = np.repeat(self.offsets[None], n, axis=0)
        for name in dict.fromkeys(e.name for e in self.entries):
            values = offsets if name == OFFSET else np.repeat(self.sim.params.get(name), n, axis=0)
            for i, entry in enumerate(self.entries):
                if entry.name == name:
                    values[(slice(None),) + entry.index[1:]] = entry.coordinate.to_theta(candidates[:, i])
            if name != OFFSET:
                batch.params.set(name, values)
        boundary = self.problem.boundary
        if boundary is None:
            return np.ones((n, len(self.index)), dtype=bool)
        batch.set_volume(np.stack([boundary.volumes(o[self.index]) for o in offsets]))
        return np.stack([boundary.inside(o[self.index]) for o in offsets])

    def _score(self, batch: Simulator, inside: np.ndarray, frames: int,
               substeps: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Roll the configured ``batch`` out over ``frames`` frames and score each row."""
        obs, s = self.problem.observations, self.settings
        n = batch.n_batch
        try:
            traj = batch.rollout(frames, substeps=substeps)
        except SimulationDiverged as error:
            _LOG.warning("a rollout diverged (%s); its candidates are left out", error)
            return np.full(n, np.nan), np.full((n, obs.n_objects), np.nan)

        def frame_loss(job: tuple[int, int]) -> tuple[float, np.ndarray]:
            b, f = job
            value, _, per = geometry_loss(traj[f, b, inside[b]].astype(np.float64),
                                          self.index[inside[b]], obs.points[f],
                                          s.per_object_loss, obs.trees(f))
            return s.chamfer_weight * value, s.chamfer_weight * per

        # KD-tree queries release the GIL: score candidates and frames in threads
        jobs = [(b, f) for b in range(n) for f in range(1, frames + 1)]
        with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
            scored = list(pool.map(frame_loss, jobs))
        total = np.array([value for value, _ in scored]).reshape(n, frames).mean(axis=1)
        per = np.stack([per for _, per in scored]).reshape(n, frames, -1).mean(axis=1)
        if s.silhouette_weight > 0 and obs.masks:
            for b in range(n):  # as _window_loss: the particles inside the surface
                silhouette = s.silhouette_weight / frames * silhouette_object_losses(
                    traj[1:frames + 1, b][:, inside[b]], self.index[inside[b]], obs.object_ids,
                    obs.views, obs.masks[1:frames + 1], s.splat_radius, s.per_object_loss,
                    self.torch_device)
                total[b] += silhouette.sum()
                per[b] += silhouette  # NaN stays NaN: the scene-level loss has no shares
        return total, per

    def _search_box(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper coordinates the search samples (see the module docstring)."""
        lo, hi = np.empty(len(u)), np.empty(len(u))
        for i, entry in enumerate(self.entries):
            if entry.name in SEARCH_RANGES:
                ends = [float(entry.coordinate.to_u(v)) for v in SEARCH_RANGES[entry.name]]
                lo[i], hi[i] = min(ends), max(ends)
            else:
                half = (self.settings.search_decades * np.log(10.0)
                        if entry.coordinate.kind == "log" else 2.0)
                lo[i], hi[i] = u[i] - half, u[i] + half
        return lo, hi

    def _best(self, current: np.ndarray, candidates: np.ndarray, velocity: np.ndarray,
              groups: list[list[int]], keep: int = 1) -> list[tuple[np.ndarray, float]]:
        """The ``keep`` best of ``current``, ``candidates`` and their per-object composite.

        ``groups[k]``: the coordinates (columns) object k's loss chooses. The candidates are
        scored as ``batch_object_losses`` does by default (on a GPU in one batch, at the time
        step of its stiffest row); the contenders (``current``, the composite and the ``keep``
        best candidates) are then compared each at its own time step, as the gradient fit will
        see them (the loss of one parameter set differs by up to 10 % between time steps, more
        than a search step gains). Best first, as (u, loss); empty if every candidate diverged.
        """
        s = self.settings
        total, per = self.batch_object_losses(candidates, velocity, s.search_frames)
        if np.all(np.isnan(total)):
            return []
        ranked = [candidates[i] for i in np.argsort(total)[:keep] if not np.isnan(total[i])]
        composite = ranked[0].copy()
        if not np.all(np.isnan(per)):
            for k, columns in enumerate(groups):
                if columns and not np.all(np.isnan(per[:, k])):
                    composite[columns] = candidates[int(np.nanargmin(per[:, k])), columns]
        contenders = [current]
        for u in [composite, *ranked]:
            if not any(np.allclose(u, c) for c in contenders):
                contenders.append(u)
        if len(contenders) == 1:
            return [(current.copy(), float(np.nanmin(total)))]
        losses = self.batch_object_losses(np.array(contenders), velocity, s.search_frames,
                                          together=False)[0]
        order = [i for i in np.argsort(losses) if not np.isnan(losses[i])]
        return [(contenders[i].copy(), float(losses[i])) for i in order[:keep]]

    def _search(self, velocity: np.ndarray) -> np.ndarray:
        """Latin-hypercube rounds in ever narrower boxes (see the module docstring); return u."""
        s = self.settings
        u = self._pack()
        lo, hi = self._search_box(u)
        n_objects = len(self.problem.objects)
        per_object = [[i for i, e in enumerate(self.entries) if e.per_object and e.index[1] == k]
                      for k in range(n_objects)]
        rng = np.random.default_rng(0)
        ranged = np.array([e.name in SEARCH_RANGES for e in self.entries])

        def round_(centre: np.ndarray, number: int, keep: int) -> list[tuple[np.ndarray, float]]:
            half = 0.5 * (hi - lo) / 3.0**number
            box_lo, box_hi = (lo, hi) if number == 0 else (centre - half, centre + half)
            box_lo = np.where(ranged, np.maximum(box_lo, lo), box_lo)
            box_hi = np.where(ranged, np.minimum(box_hi, hi), box_hi)
            # Latin hypercube: every coordinate's range cut into as many strata as samples,
            # one sample per stratum, strata paired at random across coordinates
            strata = np.stack([rng.permutation(s.search_samples) for _ in centre], axis=1)
            unit = (strata + rng.random(strata.shape)) / s.search_samples
            return self._best(centre, box_lo + (box_hi - box_lo) * unit, velocity, per_object, keep)

        def searched(done: int) -> None:  # rounds of samples scored, of ``rounds``
            self.report({"phase": "search", "done": done * s.search_samples,
                         "total": rounds * s.search_samples})

        if s.search_samples > 0:
            rounds = 1 + max(1, s.search_starts) * s.search_rounds  # fewer if starts diverge
            searched(0)
            # the first round's best points are the starts: each narrows on its own basin
            starts = round_(u, 0, max(1, s.search_starts))
            rounds = 1 + len(starts) * s.search_rounds
            searched(1)
            ends = []
            for k, (start, loss) in enumerate(starts):
                for number in range(1, s.search_rounds + 1):
                    found = round_(start, number, 1)
                    if found:
                        start, loss = found[0]
                    searched(1 + k * s.search_rounds + number)
                _LOG.info("search start %d of %d: loss %.3g: %s", k + 1, len(starts), loss,
                          self._values_of(start))
                ends.append((loss, start))
            if ends:
                u = min(ends, key=lambda end: end[0])[1]
        self._apply(u, velocity)
        return u

    # --- the fit -----------------------------------------------------------------------------

    def run(self) -> FitResult:
        obs, s = self.problem.observations, self.settings
        n = obs.n_frames - 1
        velocity = np.zeros((obs.n_objects, 6))
        velocity[:, :3] = obs.initial_velocities()
        if self.problem.initial_velocity is not None:
            known = np.isfinite(self.problem.initial_velocity[:, 0])
            velocity[known, :3] = self.problem.initial_velocity[known]
        u = self._pack()
        adam = _Adam(np.r_[np.full(len(u), s.learning_rate),
                           np.full(velocity.size, s.velocity_learning_rate)])
        history: list[dict] = []
        stage0, iteration0, failures, search_s = 0, 0, 0, 0.0
        signature = self._signature()
        resumed = self._load_checkpoint(signature)
        if resumed is not None:
            u, velocity, adam, history, stage0, iteration0, failures = resumed
            _LOG.info("resuming identification from %s: stage %d, iteration %d",
                      self.settings.checkpoint_dir, stage0, iteration0)
        elif self.problem.warm_start is not None:
            u, velocity = (np.array(a, dtype=np.float64) for a in self.problem.warm_start)
            self._apply(u, velocity)
            self.start = (u.copy(), velocity.copy())
        else:
            tick = time.perf_counter()
            u = self._search(velocity)
            search_s = time.perf_counter() - tick
            self.start = (u.copy(), velocity.copy())
        moving = np.linalg.norm(velocity[:, :3], axis=1) > 0
        stages = [h if 0 < h < n else n for h in s.curriculum]
        for stage in range(stage0, len(stages)):
            length = stages[stage]
            starts = sorted({int(round(x)) for x in np.linspace(0, n - length,
                                                                 min(s.windows, n - length + 1))})
            if length == n:
                starts = [0]
            anchor: dict[int, SimState] = {}
            for iteration in range(iteration0 if stage == stage0 else 0, s.iterations):
                tick = time.perf_counter()
                self._apply(u, velocity)
                start = starts[iteration % len(starts)]
                try:
                    if start > 0 and (start not in anchor or iteration % s.resync_every == 0):
                        anchor = {}  # a diverging anchor rollout leaves none to reuse
                        anchor = self._anchor(starts)
                    initial = self._resynced(anchor, start) if start > 0 else None
                    loss, du, dv, per = self._window_loss(start, length, initial, grad=True)
                except SimulationDiverged as error:
                    failures += 1
                    adam.lr *= 0.5
                    u, velocity, back = self._retreat(adam, u, velocity)
                    _LOG.warning("iteration %d diverged (%s); %s, learning rates halved",
                                 iteration, error, back)
                    continue
                if start == 0 and length == n and loss < self.best[0]:
                    self.best = (loss, u.copy(), velocity.copy(), per.copy())
                if not s.fit_velocity:
                    dv[:] = 0.0
                dv[~moving] = 0.0  # an object found at rest stays at rest at t = 0
                step = adam.step(np.concatenate([du, dv.ravel()]))
                moved = self._project(u + step[: len(u)])
                adam.last[: len(u)] = moved - u  # the step taken, for an undo
                u, velocity = moved, velocity + step[len(u):].reshape(velocity.shape)
                record = {"stage": stage, "window": length, "start": start, "iteration": iteration,
                          "loss": loss, "values": self._values_of(u),
                          "seconds": time.perf_counter() - tick, **self.timing}
                history.append(record)
                self.report({"phase": "fit", "done": stage * s.iterations + iteration + 1,
                             "total": len(stages) * s.iterations, **record})
                self._save_checkpoint(signature, u, velocity, adam, history, stage,
                                      iteration + 1, failures)
        u, velocity, loss, per = self._final(u, velocity, bool(history))
        values = {name: self.offsets.copy() if name == OFFSET else self.sim.params.get(name)[0]
                  for name in dict.fromkeys(e.name for e in self.entries)}
        return FitResult(values, self.entries, u, velocity, loss, per, history, failures, search_s)

    def _final(self, u: np.ndarray, velocity: np.ndarray,
               iterated: bool) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
        """The fit's result: (u, velocity, whole-window loss, per-object losses), applied.

        After gradient steps (``iterated``) the lowest of Adam's last step, the search's result
        and the best whole-window iterate: the last step need not be the best point over the
        whole window, and nothing has simulated it yet, so it may diverge (a point that does
        loses to the others rather than ending the fit).
        """
        n = self.problem.observations.n_frames - 1
        candidates = {"Adam's last step": (u, velocity)}
        if iterated:
            candidates["the search's result"] = self.start
        points = {}
        for label, (point_u, point_velocity) in candidates.items():
            self._apply(point_u, point_velocity)
            try:
                loss, _, _, per = self._window_loss(0, n, None, grad=False)
            except SimulationDiverged as error:
                if not iterated:
                    raise
                _LOG.warning("%s diverged over the whole window (%s)", label, error)
                continue
            points[label] = (loss, point_u, point_velocity, per)
        if iterated:
            points["the best whole-window iterate"] = self.best  # its loss is known
        label = min(points, key=lambda key: points[key][0])
        loss, u, velocity, per = points[label]
        if not math.isfinite(loss):
            raise SimulationError("every point the fit reached diverged over the whole window")
        if label != "Adam's last step":
            _LOG.info("keeping %s (loss %.3g) over the gradient fit's end", label, loss)
        self._apply(u, velocity)
        return u, velocity, loss, per

    def _retreat(self, adam: _Adam, u: np.ndarray,
                 velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
        """Where to go after a diverged iteration: (u, velocity, what was done).

        Adam's last step is undone; if there is none (the point passed one window and diverged
        on another, or a step was undone already), back to the lowest whole-window point seen,
        else the search's: undoing nothing would try the same point again and again.
        """
        if adam.last.any():
            return (*adam.undo(u, velocity), "step undone")
        points = [("the best whole-window point", *self.best[1:3])] if math.isfinite(self.best[0]) else []
        points.append(("the search's point", *self.start))  # empty before the search
        for label, point_u, point_velocity in points:
            if len(point_u) and not np.array_equal(point_u, u):
                return point_u.copy(), point_velocity.copy(), f"back to {label}"
        return u, velocity, "nothing to undo"

    def _project(self, u: np.ndarray) -> np.ndarray:
        """The coordinates moved back inside their ranges (projected Adam).

        Past a bound theta stops changing, so u would drift on where nothing pulls it back.
        """
        return np.array([e.coordinate.clip_u(v) for e, v in zip(self.entries, u, strict=True)])

    def _values_of(self, u: np.ndarray) -> dict[str, float]:
        return {e.label: float(e.coordinate.to_theta(v)) for e, v in zip(self.entries, u, strict=True)}

    # --- checkpoints -------------------------------------------------------------------------

    def _signature(self) -> str:
        obs = self.problem.observations
        text = json.dumps({
            "objects": [(o.name, o.family) for o in self.problem.objects],
            "free": [e.label for e in self.entries], "frames": obs.n_frames,
            "frame_dt": obs.frame_dt, "particles": int(len(self.index)),
            "centroids": np.round(np.nan_to_num(self.observed_centroids), 6).tolist(),
            "settings": self.settings.result_settings(),
            "initial_velocity": _rounded(self.problem.initial_velocity),
            "warm_start": [_rounded(a) for a in self.problem.warm_start or ()],
        })
        return hashlib.sha256(text.encode()).hexdigest()

    def _save_checkpoint(self, signature, u, velocity, adam, history, stage, iteration,
                         failures) -> None:
        if not self.settings.checkpoint_dir:
            return
        directory = Path(self.settings.checkpoint_dir)
        directory.mkdir(parents=True, exist_ok=True)
        with replacing(directory / CHECKPOINT_FILE) as tmp:
            np.savez(tmp, signature=signature, u=u, velocity=velocity, start_u=self.start[0],
                     start_velocity=self.start[1], best_loss=self.best[0], best_u=self.best[1],
                     best_velocity=self.best[2], best_per=self.best[3], m=adam.m, v=adam.v,
                     t=adam.t, lr=adam.lr, stage=stage, iteration=iteration, failures=failures,
                     history=json.dumps(history))

    def _load_checkpoint(self, signature: str):
        if not self.settings.checkpoint_dir:
            return None
        path = Path(self.settings.checkpoint_dir) / CHECKPOINT_FILE
        if not path.is_file():
            return None
        try:
            data = np.load(path)
            if str(data["signature"]) != signature:
                _LOG.warning("%s belongs to another problem or settings; starting afresh", path)
                return None
            self.start = (data["start_u"], data["start_velocity"])
            self.best = (float(data["best_loss"]), data["best_u"], data["best_velocity"],
                         data["best_per"])
            adam = _Adam(data["lr"])
            adam.m, adam.v, adam.t = data["m"], data["v"], int(data["t"])
            return (data["u"], data["velocity"], adam, json.loads(str(data["history"])),
                    int(data["stage"]), int(data["iteration"]), int(data["failures"]))
        except (OSError, EOFError, KeyError, ValueError, zipfile.BadZipFile) as error:  # partial or corrupt
            _LOG.warning("cannot read checkpoint %s (%s: %s); starting afresh", path,
                         type(error).__name__, error)
            return None


def _rounded(a: np.ndarray | None) -> list | None:
    return None if a is None else np.round(np.nan_to_num(np.asarray(a, dtype=np.float64)), 9).tolist()


def _component(name: str) -> tuple[str, int | None]:
    """``"wind.a[1]"`` -> ("wind.a", 1): one component of a vector parameter; else (name, None)."""
    if name.endswith("]") and "[" in name:
        base, index = name[:-1].split("[", 1)
        return base, int(index)
    return name, None


class _Adam:
    """Adam (Kingma & Ba 2015) on a flat vector, one step size per coordinate.

    It remembers its last step so that a diverged iteration can be undone.
    """

    def __init__(self, lr: np.ndarray, beta1: float = 0.9, beta2: float = 0.999) -> None:
        self.lr = np.asarray(lr, dtype=np.float64)
        self.beta1, self.beta2 = beta1, beta2
        size = len(self.lr)
        self.m, self.v, self.t = np.zeros(size), np.zeros(size), 0
        self.last = np.zeros(size)

    def step(self, grad: np.ndarray) -> np.ndarray:
        grad = np.nan_to_num(grad)
        self.t += 1
        self.m = self.beta1 * self.m + (1 - self.beta1) * grad
        self.v = self.beta2 * self.v + (1 - self.beta2) * grad * grad
        m_hat = self.m / (1 - self.beta1**self.t)
        v_hat = self.v / (1 - self.beta2**self.t)
        self.last = -self.lr * m_hat / (np.sqrt(v_hat) + 1e-12)
        return self.last

    def undo(self, u: np.ndarray, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = u - self.last[: len(u)]
        velocity = velocity - self.last[len(u):].reshape(velocity.shape)
        self.last = np.zeros_like(self.last)
        return u, velocity
