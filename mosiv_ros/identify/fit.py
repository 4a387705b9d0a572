"""Per-object material identification by differentiable MPM rollouts (MOSIV stage 3).

``Identifier(problem, settings).run()`` fits the free parameters of a ``FitProblem`` (per-object
material parameters, ground and effect parameters, and each object's initial linear and angular
velocity) to its observations with Adam on the simulator's gradients. The identifier holds the
problem and its objective; three parts do the work, each in its own module:

- ``identify.search.GlobalSearch``: before Adam, a gradient-free search in batched rollouts
  finds the basin (Latin-hypercube rounds in ever narrower boxes, from several starts); ends
  whose losses lie within ``search.race`` of the best each run the curriculum's first stage,
  and the one that fits best there goes on (``Curriculum.race``);
- ``identify.curriculum.Curriculum``: Adam over a horizon curriculum of windows, each window
  after the first resynchronised onto the observed centroids, a diverging step undone;
- ``identify.checkpoint.Checkpoint``: with a checkpoint directory the state is written after
  every iteration and a rerun of the same problem resumes from it.

What the identifier itself does:

- coordinates: each parameter moves in ``identify.coordinates`` (log for moduli, bounded logits
  for nu and friction), velocities in m/s and rad/s; Adam's steps are projected back into each
  coordinate's range (``project``), whose top for E and the bulk modulus is ``max_modulus``
  (1 MPa): along a direction the data leave flat a modulus would otherwise climb on, and each
  iteration's cost with it (the time step shrinks as 1 / sqrt(modulus));
- initial velocities start from the observed centroid motion of the first frames (an object
  found at rest keeps a zero initial velocity; the others' are refined with the parameters);
- the objective (``window_loss``): Chamfer, silhouette and surface track terms over a window of
  frames, and their gradients with respect to the coordinates and the initial velocities; on a
  GPU all frames at once as tensors there (``tensor_device``), queued behind the rollout
  (``window_losses``), on the CPU frame by frame;
- the result is the lowest whole-window loss among the search's point, the whole-sequence
  stage's iterates and Adam's last step (a windowed stage's objective is not the whole window's,
  and Adam's last step need not be its best); a last step that diverges loses to the other
  points.

What it is for: the fit. What it is not for: choosing a family (``identify.family``),
uncertainty (``identify.estimates``), or reading bags and nodes.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, fields, replace
from functools import partial

import numpy as np
import torch

from mosiv_ros.config import FitConfig
from mosiv_ros.identify.checkpoint import Checkpoint, signature
from mosiv_ros.identify.coordinates import Coordinate
from mosiv_ros.identify.curriculum import Adam, Curriculum, FitState
from mosiv_ros.identify.losses import (
    calibrated_splat_radius,
    geometry_loss,
    queued_gradient,
    queued_positions,
    silhouette_losses,
    tensor_terms,
    torch_threads,
    track_loss,
)
from mosiv_ros.identify.observations import Observations
from mosiv_ros.identify.search import GlobalSearch
from mosiv_ros.lifting.lift import boundary_volume
from mosiv_ros.sim import Gradients, ObjectModel, Particles, SimConfig, SimState, Simulator
from mosiv_ros.sim.errors import SimulationDiverged, SimulationError
from mosiv_ros.sim.materials import FAMILY_PARAMS, MATERIAL_PARAM_NAMES
from mosiv_ros.simulation import OFFSET

_LOG = logging.getLogger(__name__)

SPLAT_SHARE = 0.5
"""The silhouette splats' radius (``losses``) in particle spacings where no mask calibrates it
(``Identifier._splat_radius``): a particle stands for a cube of one spacing, the outermost up
to half a spacing inside the surface."""

MODULI = ("E", "bulk_modulus")
"""Parameters that set the stable time step through the wave speed: ``max_modulus`` caps them."""


@dataclass
class FitSettings(FitConfig):
    """How a fit runs: identify_node's fit parameters (``config.FitConfig``) and internal settings.

    The parameters' defaults and meaning are in ``config``; no parameter sets the ones below.
    """

    fit_velocity: bool = True
    resync_every: int = 10
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
    race: list[dict] = field(default_factory=list)
    """The search's ends that ran the first curriculum stage (``search.race``), each with its
    search loss, its score there, the stage's seconds and whether it went on; empty: none ran."""


class Identifier:
    """Fits a ``FitProblem``; see the module docstring.

    Its interface to the parts and to callers that roll its simulator out themselves (family
    selection, the loop closure): ``problem``, ``settings``, ``sim`` (the fit's simulator),
    ``entries`` (the free scalars), ``index`` (each particle's object), ``offsets`` (the boundary
    offsets), ``observed_centroids``, ``pack``/``apply``/``start_from`` (coordinates <->
    simulator), ``window_loss``, ``project``, ``values_of``, ``report``, ``search`` (its
    ``GlobalSearch``, also the batched losses) and ``run``.
    """

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
        self.timing: dict[str, float] = {}
        """Of the last window: forward_s, loss_s, backward_s. On a GPU the loss is queued behind the
        rollout (``window_losses``): forward_s holds both, and loss_s the host's part of it."""
        self.torch_device = self.sim.device if self.sim.device.startswith("cuda") else "cpu"
        self.splat_radius = self._splat_radius()
        """(K,) radius (m) of each object's particle splats in the silhouette loss (``_splat_radius``)."""
        self.tensor_device: str | None = self.sim.device if self.sim.device.startswith("cuda") else None
        """Where the losses are computed as tensors, every frame (and row) at once
        (``losses.tensor_terms``): the simulator's GPU. None: on the CPU frame by frame, nearest
        neighbours by KD-tree, the silhouettes in torch on ``torch_device`` (the tests set "cpu"
        to run the tensor path there)."""
        self.search = GlobalSearch(self)
        self.curriculum = Curriculum(self)

    def _splat_radius(self) -> np.ndarray:
        """Each object's silhouette splat radius (K,): calibrated on the first frame's masks.

        ``losses.calibrated_splat_radius`` over the object's particles inside the surface at the
        first frame, the one they were lifted from; ``SPLAT_SHARE`` particle spacings for an
        object no mask of that frame shows (or without a silhouette loss).
        """
        problem = self.problem
        spacing = (float(np.cbrt(problem.boundary.lattice_volume)) if problem.boundary is not None
                   else problem.sim_config.dx / 2)  # lifting samples at half a cell
        radius = np.full(len(problem.objects), SPLAT_SHARE * spacing)
        obs = problem.observations
        if self.settings.loss.silhouette_weight <= 0 or not obs.masks:
            return radius
        inside = (problem.boundary.inside(np.zeros(len(self.index))) if problem.boundary is not None
                  else np.ones(len(self.index), dtype=bool))
        for k, (model, object_id) in enumerate(zip(problem.objects, obs.object_ids, strict=True)):
            mine = inside & (self.index == k)
            calibrated = calibrated_splat_radius(problem.particles.x[mine], object_id, obs.views, obs.masks[0],
                                                 spacing, self.torch_device)
            if calibrated is not None:
                radius[k] = calibrated
            _LOG.info("silhouette splats of %s: radius %.2f mm (%.2f particle spacings)%s", model.name,
                      radius[k] * 1e3, radius[k] / spacing,
                      ", where its first frame's particles cover the pixels its masks show"
                      if calibrated is not None else "")
        return radius

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
        self.apply(self.pack(), velocity)

    def pack(self) -> np.ndarray:
        """The coordinates (u) of the free entries' values in ``sim`` (and ``offsets``)."""
        u = [e.coordinate.to_u(self.offsets[e.index[1]] if e.name == OFFSET
                               else self.sim.params.get(e.name)[e.index]) for e in self.entries]
        return np.asarray(u, dtype=np.float64)

    def apply(self, u: np.ndarray, velocity: np.ndarray) -> None:
        """Set ``sim`` to coordinates ``u`` and initial velocities (K, 6) about each centroid."""
        values: dict[str, np.ndarray] = {}
        for entry, value in zip(self.entries, u, strict=True):
            if entry.name == OFFSET:
                self.offsets[entry.index[1]] = entry.coordinate.to_theta(value)
                continue
            if entry.name not in values:  # each parameter read once, however many entries it has
                values[entry.name] = self.sim.params.get(entry.name)
            values[entry.name][entry.index] = entry.coordinate.to_theta(value)
        self.sim.params.update(values)
        boundary = self.problem.boundary
        if boundary is not None:
            self.sim.set_volume(boundary.volumes(self.offsets[self.index]))
            self.inside = boundary.inside(self.offsets[self.index])
        self.sim.set_initial_velocity(self.particle_velocity(velocity))

    def particle_velocity(self, velocity: np.ndarray) -> np.ndarray:
        """Each particle's initial velocity (N, 3) from each object's (K, 6) about its centroid."""
        linear, angular = velocity[self.index, :3], velocity[self.index, 3:]
        return linear + np.cross(angular, self.problem.particles.x - self.centre0[self.index])

    def velocity_gradient(self, g0: np.ndarray) -> np.ndarray:
        """dL/d(object velocities) (K, 6) from dL/d(particle velocities) ``g0`` (N, 3).

        The adjoint of ``particle_velocity``.
        """
        r = self.problem.particles.x - self.centre0[self.index]
        dv = np.zeros((len(self.problem.objects), 6))
        for k in range(len(dv)):
            mine = self.index == k
            dv[k, :3] = g0[mine].sum(axis=0)
            dv[k, 3:] = np.cross(r[mine], g0[mine]).sum(axis=0)
        return dv

    def offsets_of(self, points: np.ndarray) -> np.ndarray:
        """The boundary offsets (R, K) of coordinate rows ``points`` (R, P); ``offsets`` where no entry sets them."""
        offsets = np.repeat(self.offsets[None], len(points), axis=0)
        for i, entry in enumerate(self.entries):
            if entry.name == OFFSET:
                offsets[:, entry.index[1]] = entry.coordinate.to_theta(points[:, i])
        return offsets

    def rows(self, points: list[tuple[np.ndarray, np.ndarray]]) -> tuple[Simulator, np.ndarray]:
        """A batched simulator set to ``points`` (u, velocity), a row each; (R, N) which particles are inside.

        The search's kept simulator of that many rows (``GlobalSearch.simulator``); what no entry
        sets comes from ``sim``, as ``apply`` leaves it for the first point.
        """
        self.apply(*points[0])
        batch = self.search.simulator(len(points))
        inside = self.search.configure(batch, np.stack([u for u, _ in points]))
        batch.set_initial_velocity(np.stack([self.particle_velocity(velocity) for _, velocity in points]))
        return batch, inside

    # --- one window --------------------------------------------------------------------------

    def window_loss(self, start: int, length: int, initial: SimState | None,
                     grad: bool) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Loss over frames start+1..start+length, dL/du, dL/dvelocity (K, 6), per-object losses."""
        return self.window_losses(self.sim, self.pack()[None], self.offsets[None], self.inside[None],
                                  start, length, initial, grad)[0]

    def window_losses(self, sim: Simulator, points: np.ndarray, offsets: np.ndarray, inside: np.ndarray,
                      start: int, length: int, initial: SimState | None, grad: bool,
                      own_steps: bool = False) -> list[tuple[float, np.ndarray, np.ndarray, np.ndarray]]:
        """``window_loss`` of each row of ``sim``, set to coordinates ``points`` (R, P).

        ``offsets`` (R, K) its rows' boundary offsets, ``inside`` (R, N) their particles inside
        the surface; ``own_steps``: each row at its own time step (``Simulator.rollout``). The
        rows' losses are independent, so one backward gives each its own gradients.
        """
        obs = self.problem.observations
        totals, pers, grads, self.timing = self._window_values(sim, inside, start, length, initial, grad, own_steps)
        if not grad:
            return [(float(total), np.zeros(len(self.entries)), np.zeros((obs.n_objects, 6)), per)
                    for total, per in zip(totals, pers, strict=True)]
        boundary = self.problem.boundary
        results = []
        for row, (u, total, per) in enumerate(zip(points, totals, pers, strict=True)):
            if boundary is not None:
                dL_do = grads.volume[row] * boundary.dvolume_doffset(offsets[row][self.index])
                offset_grads = np.bincount(self.index, dL_do, minlength=obs.n_objects)
            du = np.array([(offset_grads[e.index[1]] if e.name == OFFSET
                            else grads.params[e.name][(row, *e.index[1:])])
                           * e.coordinate.dtheta_du(u[i]) for i, e in enumerate(self.entries)])
            # velocities are parameters only of windows from frame 0
            dv = self.velocity_gradient(grads.v0[row]) if initial is None else np.zeros((obs.n_objects, 6))
            results.append((float(total), du, dv, per))
        return results

    def _window_values(self, sim: Simulator, inside: np.ndarray, start: int, length: int,
                       initial: SimState | None, grad: bool,
                       own_steps: bool) -> tuple[np.ndarray, np.ndarray, Gradients | None, dict[str, float]]:
        """``window_losses``' rollout, loss and backward: the rows' losses, per-object losses, gradients, timing.

        Each row's loss (R,) and per-object losses (R, K), the simulator's gradients (with
        ``grad``, else None) and the timing (``self.timing``). On a GPU the loss is queued
        behind the rollout, its host work done while the device simulates, and read once the
        backward is queued; on the CPU it follows the rollout.
        """
        tick = time.perf_counter()
        if self.tensor_device is None:
            traj = sim.rollout(length, grad=grad, initial=initial, start_frame=start, own_steps=own_steps)
            timing = {"forward_s": time.perf_counter() - tick}
            tick = time.perf_counter()
            totals, dL, pers = self._loss_of(traj, start, inside)
            timing["loss_s"] = time.perf_counter() - tick
        else:
            queued = sim.queue_rollout(length, grad=grad, initial=initial, start_frame=start, own_steps=own_steps)
            queued_at = time.perf_counter()
            x = queued_positions(queued.positions, sim.n_batch, sim.n_particles, self.tensor_device)
            terms = self._tensor_window(x, start, inside, grad)
            timing = {"loss_s": time.perf_counter() - queued_at}
            queued.wait()
            timing["forward_s"] = time.perf_counter() - tick
            dL = queued_gradient(terms[2], self.tensor_device) if grad else None
        grads = None
        if grad:
            tick = time.perf_counter()
            grads = sim.backward(dL)
            timing["backward_s"] = time.perf_counter() - tick
        if self.tensor_device is not None:  # read once the backward is queued behind the loss
            totals, pers = (value.cpu().numpy() for value in terms[:2])
        return totals, pers, grads, timing

    def _loss_of(self, traj: np.ndarray, start: int, inside: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """On the CPU, each row's loss of rollout ``traj`` (frames ``start``.. on), frame by frame.

        Returns the losses (R,), dL/dx like ``traj`` and the per-object losses (R, K).
        ``inside`` (R, N): which particles of each row are inside the surface (``self.inside``
        for ``sim``'s).
        """
        rows = [self._frame_losses(traj[:, r:r + 1], start, inside[r]) for r in range(traj.shape[1])]
        return (np.array([total for total, _, _ in rows]), np.concatenate([dL for _, dL, _ in rows], axis=1),
                np.stack([per for *_, per in rows]))

    def _frame_losses(self, traj: np.ndarray, start: int,
                      inside: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """``_loss_of`` of one row on the CPU, frame by frame.

        Chamfer by KD-tree, the silhouettes in batches of frames, the tracks.
        """
        obs, s = self.problem.observations, self.settings
        length = len(traj) - 1
        dL = np.zeros(traj.shape, dtype=np.float64)
        total, per = 0.0, np.zeros(obs.n_objects)
        for f in range(1, length + 1):
            x = traj[f, 0].astype(np.float64)
            value, g, per_f = geometry_loss(x[inside], self.index[inside], obs.points[start + f],
                                            s.loss.per_object, obs.trees(start + f))
            total += s.loss.chamfer_weight * value
            dL[f, 0, inside] = s.loss.chamfer_weight * g
            per += np.nan_to_num(per_f)
        if s.loss.silhouette_weight > 0 and obs.masks:
            # the particles the Chamfer scores, not the boundary band outside the surface
            value, g = silhouette_losses(traj[1:, 0][:, inside], self.index[inside], obs.object_ids,
                                         obs.views, obs.masks[start + 1: start + length + 1],
                                         self.splat_radius, s.loss.per_object, self.torch_device)
            total += s.loss.silhouette_weight * value
            dL[1:, 0, inside] += s.loss.silhouette_weight * g
        if s.loss.track_weight > 0 and obs.tracks is not None:
            for f in range(1, length + 1):  # every particle: a track may hold on to the band
                value, g, per_f = track_loss(traj[f, 0].astype(np.float64), obs.tracks, start + f,
                                             s.loss.track_scale, obs.n_objects)
                total += s.loss.track_weight * value
                dL[f, 0] += s.loss.track_weight * g
                per += s.loss.track_weight * per_f
        return total / length, dL / length, per / length

    def _tensor_window(self, x: torch.Tensor, start: int, inside: np.ndarray,
                       grad: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Each row's loss (R,), per-object losses (R, K) and dL/dx (or None) of ``x``, as tensors.

        ``x`` (R, F, N, 3) float64 the rows' particles at frames ``start`` + 1.. on
        ``tensor_device``. Nothing here waits for the device (``tensor_terms``).
        """
        obs, loss, device = self.problem.observations, self.settings.loss, self.tensor_device
        length = x.shape[1]
        with torch_threads(device), torch.set_grad_enabled(grad):
            x.requires_grad_(grad)
            terms = tensor_terms(x, inside, self.index, obs.tensors(device), obs.object_ids,
                                 slice(start + 1, start + length + 1), loss, self.splat_radius)
            total = (loss.chamfer_weight * terms.chamfer_total.sum(dim=1) + loss.silhouette_weight
                     * terms.silhouette.sum(dim=1) + loss.track_weight * terms.track.sum(dim=(1, 2))) / length
            per = (terms.chamfer.nan_to_num().sum(dim=1) + loss.track_weight * terms.track.sum(dim=1)) / length
            if grad:
                total.sum().backward()
        return total.detach(), per.detach(), x.grad if grad else None

    # --- the fit -----------------------------------------------------------------------------

    def run(self) -> FitResult:
        """Search (or resume, or start warm), iterate the curriculum, keep the best point."""
        obs, s = self.problem.observations, self.settings
        velocity = np.zeros((obs.n_objects, 6))
        velocity[:, :3] = obs.initial_velocities()
        if self.problem.initial_velocity is not None:
            known = np.isfinite(self.problem.initial_velocity[:, 0])
            velocity[known, :3] = self.problem.initial_velocity[known]
        u = self.pack()
        adam = Adam(np.r_[np.full(len(u), s.curriculum.learning_rate),
                          np.full(velocity.size, s.curriculum.velocity_learning_rate)])
        search_s, race = 0.0, []
        checkpoint = Checkpoint(s.checkpoint_dir, signature(
            self.problem, [e.label for e in self.entries], s.result_settings()))
        state = checkpoint.load()
        if state is not None:
            _LOG.info("resuming identification from %s: stage %d, iteration %d",
                      s.checkpoint_dir, state.stage, state.iteration)
        elif self.problem.warm_start is not None:
            u, velocity = (np.array(a, dtype=np.float64) for a in self.problem.warm_start)
            self.apply(u, velocity)
            state = FitState(u, velocity, adam, (u.copy(), velocity.copy()))
        else:
            tick = time.perf_counter()
            ends = self.search.run(velocity, checkpoint)
            search_s = time.perf_counter() - tick
            state, race = self._raced(ends, velocity, adam)
            # stopped before its first iteration after the search and the race ends, it resumes
            # here; stopped in the race, it races again from the search's checkpoint
            checkpoint.save(state)
        extra = self.curriculum.raced(len(race))  # the race's iterations, counted in the progress
        state = self.curriculum.run(state, checkpoint.save, before=extra, raced=extra)
        u, velocity, loss, per = self._final(state)
        values = {name: self.offsets.copy() if name == OFFSET else self.sim.params.get(name)[0]
                  for name in dict.fromkeys(e.name for e in self.entries)}
        return FitResult(values, self.entries, u, velocity, loss, per, state.history, state.failures,
                         search_s, race)

    def _raced(self, ends: list[tuple[np.ndarray, float]], velocity: np.ndarray,
               adam: Adam) -> tuple[FitState, list[dict]]:
        """The state Adam goes on from after the search's ``ends`` (best first), and the race's record.

        The best end, unless others score within ``search.race`` of its loss: then each of those
        runs the curriculum's first stage and the one that fits best there goes on
        (``Curriculum.race``). The search's losses do not rank ends that close reliably: on
        cube_on_slab, of three ends 1.9 % apart, the one the search scored worst finished Adam
        lowest (benchmarks/RESULTS.md).
        """
        s = self.settings
        racers = ends[:1]
        for u, loss in ends[1:]:
            close = s.search.race > 0 and loss <= ends[0][1] * (1 + s.search.race)
            if close and not any(np.array_equal(u, other) for other, _ in racers):
                racers.append((u, loss))
        if len(racers) == 1 or not self.curriculum.stages() or s.curriculum.iterations == 0:
            u = ends[0][0]
            return FitState(u, velocity, adam, (u.copy(), velocity.copy())), []
        states = [FitState(u.copy(), velocity.copy(), copy.deepcopy(adam), (u.copy(), velocity.copy()))
                  for u, _ in racers]
        won, scores = self.curriculum.race(states)
        race = [{"search_loss": loss, "stage_loss": score,
                 "seconds": sum(h["seconds"] for h in state.history), "went_on": k == won}
                for k, ((_, loss), state, score) in enumerate(zip(racers, states, scores, strict=True))]
        _LOG.info("the search's %d closest ends each ran the first stage (%d-frame windows): losses %s; "
                  "end %d went on", len(states), self.curriculum.stages()[0],
                  ", ".join(f"{r['search_loss']:.4g} -> {r['stage_loss']:.4g}" for r in race), won + 1)
        return states[won], race

    def _final(self, state: FitState) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
        """The fit's result: (u, velocity, whole-window loss, per-object losses), applied.

        After gradient steps (a ``history``) the lowest of Adam's last step, the search's result
        and the best whole-window iterate: the last step need not be the best point over the
        whole window, and nothing has simulated it yet, so it may diverge (a point that does
        loses to the others rather than ending the fit).
        """
        iterated = bool(state.history)
        candidates = {"Adam's last step": (state.u, state.velocity)}
        if iterated:
            candidates["the search's result"] = state.start
        points = {}
        for (label, (point_u, point_velocity)), scored in zip(
                candidates.items(), self._whole_window(list(candidates.values())), strict=True):
            if isinstance(scored, SimulationDiverged):
                if not iterated:
                    raise scored
                _LOG.warning("%s diverged over the whole window (%s)", label, scored)
                continue
            points[label] = (scored[0], point_u, point_velocity, scored[1])
        if iterated:
            points["the best whole-window iterate"] = state.best  # its loss is known
        label = min(points, key=lambda key: points[key][0])
        loss, u, velocity, per = points[label]
        if not math.isfinite(loss):
            raise SimulationError("every point the fit reached diverged over the whole window")
        if label != "Adam's last step":
            _LOG.info("keeping %s (loss %.3g) over the gradient fit's end", label, loss)
        self.apply(u, velocity)
        return u, velocity, loss, per

    def _whole_window(self, points: list[tuple[np.ndarray, np.ndarray]]) -> list:
        """Each (u, velocity)'s whole-window loss and per-object losses, or what stopped its rollout.

        The values ``window_loss`` gives, or the ``SimulationDiverged``. The first point rolls
        out on ``sim``; on the CPU the others roll out beside it, each on a simulator of the
        search's set up from ``sim`` as its rows are (a rollout repeats to the bit, whichever
        simulator runs it).
        """
        n = self.problem.observations.n_frames - 1
        cpu = self.sim.device == "cpu"

        def scored(sim: Simulator, inside: np.ndarray) -> tuple[float, np.ndarray] | SimulationDiverged:
            try:
                total, per, _, _ = self._window_values(sim, inside[None], 0, n, None, False, False)
            except SimulationDiverged as error:
                return error
            return float(total[0]), per[0]

        if not cpu:  # one point after the other on ``sim``
            results = []
            for u, velocity in points:
                self.apply(u, velocity)
                results.append(scored(self.sim, self.inside))
            return results
        for f in range(1, n + 1):  # built once, before threads share them
            self.problem.observations.trees(f)
        jobs = []
        for slot, (u, velocity) in reversed(list(enumerate(points))):  # ``sim``'s point set up last
            self.apply(u, velocity)
            if slot == 0:
                jobs.append(partial(scored, self.sim, self.inside))
            else:
                batch = self.search.simulator(1, slot)
                jobs.append(partial(scored, batch, self.search.configure(batch, u[None])[0]))
        with ThreadPoolExecutor(max_workers=len(jobs)) as pool:
            return list(pool.map(lambda job: job(), reversed(jobs)))

    def project(self, u: np.ndarray) -> np.ndarray:
        """The coordinates moved back inside their ranges (projected Adam).

        Past a bound theta stops changing, so u would drift on where nothing pulls it back.
        """
        return np.array([e.coordinate.clip_u(v) for e, v in zip(self.entries, u, strict=True)])

    def values_of(self, u: np.ndarray) -> dict[str, float]:
        """The parameter value of each free entry at coordinates ``u``, by label."""
        return {e.label: float(e.coordinate.to_theta(v)) for e, v in zip(self.entries, u, strict=True)}


def _component(name: str) -> tuple[str, int | None]:
    """``"wind.a[1]"`` -> ("wind.a", 1): one component of a vector parameter; else (name, None)."""
    if name.endswith("]") and "[" in name:
        base, index = name[:-1].split("[", 1)
        return base, int(index)
    return name, None
