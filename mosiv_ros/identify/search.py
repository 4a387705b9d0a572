"""The gradient-free search before Adam, and the batched losses it scores with (MOSIV stage 3).

``GlobalSearch(identifier).run(velocity, checkpoint)`` returns the points found (the starts' ends,
best first, with their losses), and leaves the identifier's simulator set to the best. All its
candidates are simulated in batched rollouts of the first ``search.frames`` frames (0 = all):

- ``search.samples`` points of a Latin hypercube over a box (``box``), which for a material
  parameter is its prior range ``SEARCH_RANGES`` (a yield stress far above the true one leaves
  the loss flat, so no gradient finds the way down: the samples must land below it) and
  otherwise the initial value +- ``search_decades`` decades (scale parameters) or 2 logit units;
- samples are scored by the objective Adam minimises (Chamfer, silhouette and track terms,
  ``batch_object_losses``; on a GPU every row and frame of a batch at once, as tensors). The
  best sample is kept; with per-object losses, so is the composite that takes each object's
  parameters from the sample that fits that object best (each object's loss depends mostly on
  its own parameters, so 32 samples search each object's few dimensions rather than all
  objects' together), whichever of the two fits better (``best``);
- the ``search.starts`` best points of this first round are the starts: each then goes through
  ``search.rounds`` more such rounds (the starts' rounds side by side, their contenders scored
  together), each in a box 3x narrower than the last around its best so far (samples that
  move every coordinate at once follow the valleys of coupled parameters, such as E and nu,
  which one-coordinate-at-a-time passes stall in), and the ends are returned lowest first (the
  fit runs those within ``search.race`` of the lowest through its first stage to choose,
  ``Identifier``).
  Several starts keep other basins alive: coupled parameters can explain the same motion twice
  (on elastic_on_plastic one start narrowed onto a clay yield stress of 456 Pa with a ground
  friction of 1.9, at a higher loss than the true 800 Pa and 0.5), and the first round's best
  need not lie in the basin of lowest loss.

The identifier (``identify.fit.Identifier``) supplies the problem, the settings, the free
entries and its simulator's state, which rows of a batch start from.

What it is for: finding the basin, and the loss of many parameter sets at once (also the
uncertainty's, ``identify.estimates``). What it is not for: gradient steps
(``identify.curriculum``).
"""

from __future__ import annotations

import itertools
import logging
import math
import os
import queue
import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
import torch

from mosiv_ros.identify.losses import (
    geometry_loss,
    queued_positions,
    silhouette_object_losses,
    tensor_terms,
    torch_threads,
    track_loss,
)
from mosiv_ros.sim import Simulator
from mosiv_ros.sim.errors import SimulationDiverged
from mosiv_ros.simulation import OFFSET

if TYPE_CHECKING:
    from mosiv_ros.identify.checkpoint import Checkpoint
    from mosiv_ros.identify.fit import Identifier

_LOG = logging.getLogger(__name__)

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


class GlobalSearch:
    """The search of ``identifier``'s problem; see the module docstring."""

    def __init__(self, identifier: Identifier) -> None:
        self.identifier = identifier
        self.simulators: dict[tuple[int, int], Simulator] = {}
        """The batched simulators kept, by (rows, worker slot)."""
        self.timing: dict[str, float] = {}
        """Of the last ``batch_object_losses``: ``rollout_s`` and ``score_s``, each summed over its
        rollouts (on several CPU cores the sums exceed the wall time). On a GPU the scoring is
        queued behind the rollout (``_score``): ``rollout_s`` holds both, ``score_s`` the reading."""
        self.own_step_batches = identifier.sim.device.startswith("cuda")
        """Whether rows that each take their own time step go in one batched rollout whose rows
        step on their own (``Simulator.rollout(own_steps=True)``): on a GPU, where a batch costs
        about what its stiffest row does; on the CPU each row runs alone, side by side."""

    def batch_losses(self, candidates: np.ndarray, velocity: np.ndarray,
                     frames: int | None = None, together: bool | None = None) -> np.ndarray:
        """The fit's loss of each row of ``candidates`` (coordinate vectors, (B, P)).

        The same objective as Adam's (weighted Chamfer, silhouette and track terms, mean over frames),
        without gradients.

        ``together`` (default: on a GPU): every row at the time step of the stiffest row, in one
        batched rollout; else each row at its own stable time step (on the CPU a batch costs as
        much as its rows, and the loss of one parameter set differs by up to 10 % between time
        steps), on a GPU in one batched rollout whose rows take their own steps
        (``Simulator.rollout(own_steps=True)``, ``own_step_batches``; one row after another in a
        scene with colliders). On the CPU the rows, or slices of them when together, are
        simulated side by side, one simulator per core (``FitSettings.cpu_workers``). Over
        frames 1..``frames`` (default all); NaN where a rollout diverged (every row of its batch
        or slice).

        The GPU's default keeps the stiffest row's step: scored at their own steps, the search's
        rows of elastic_on_plastic led it to another basin (benchmarks/RESULTS.md, "Search rows at
        their own time steps"). Where a row of a batch at their own steps diverges, the rows are
        scored again one at a time, so that only it is NaN.
        """
        return self.batch_object_losses(candidates, velocity, frames, together)[0]

    def batch_object_losses(self, candidates: np.ndarray, velocity: np.ndarray,
                            frames: int | None = None, together: bool | None = None,
                            substeps: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``batch_losses`` and each object's share of them, (B,) and (B, K).

        The shares are NaN with the scene-level (ablation) loss, which does not split by object.
        ``substeps``: every row at this many substeps per frame, together (refused below a row's
        stability bound); by default the stiffest row's when together.
        """
        own = (self.own_step_batches and together is False and substeps is None
               and self.identifier.sim.own_steps_allowed)
        return self._losses(candidates, velocity, frames, together, substeps, own)

    def _losses(self, candidates: np.ndarray, velocity: np.ndarray, frames: int | None,
                together: bool | None, substeps: int | None, own: bool) -> tuple[np.ndarray, np.ndarray]:
        """``batch_object_losses``; ``own``: the rows, each at its own step, in one batch."""
        fit = self.identifier
        obs = fit.problem.observations
        frames = min(frames or obs.n_frames - 1, obs.n_frames - 1)
        cuda = fit.sim.device.startswith("cuda")
        together = self._together(together, substeps, own)
        fit.apply(candidates[0], velocity)  # the rows' common set-up: initial velocity, fixed values
        if fit.tensor_device is not None:  # built once, before threads share them
            obs.tensors(fit.tensor_device)
        else:
            for f in range(1, frames + 1):
                obs.trees(f)
        # On the CPU each simulator runs on one core and its kernels release the GIL, so rows (or
        # slices of a batch) run side by side on every core, with the same results as in turn.
        workers = 1 if cuda else max(1, min(len(candidates), fit.settings.cpu_workers or os.cpu_count() or 1))
        if together:  # one batch: the stiffest row's time step for every row, or each row's own
            groups = [candidates] if cuda else np.array_split(candidates, workers)
            sims = [self.simulator(len(g), slot) for slot, g in enumerate(groups)]
            insides = [self.configure(sim, g) for sim, g in zip(sims, groups, strict=True)]
            substeps = None if own else substeps or max(sim.time_step()[0] for sim in sims)
            jobs = [partial(self._score, sim, inside, frames, substeps, own)
                    for sim, inside in zip(sims, insides, strict=True)]
        else:  # each row at its own time step, on the simulator of a free slot
            idle = queue.SimpleQueue()
            for slot in range(workers):
                idle.put(self.simulator(1, slot))

            def one(row: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
                sim = idle.get()
                try:
                    return self._score(sim, self.configure(sim, row[None]), frames)
                finally:
                    idle.put(sim)

            jobs = [partial(one, row) for row in candidates]
        # the costliest first (a row's cost is its substeps per frame), so that the cores finish
        # together; the results in the rows' order
        order = self._costliest_first(candidates) if workers > 1 and not together else range(len(jobs))
        if workers == 1:  # the GPU's one batch, or one core: in this thread, as before the threads
            results = [job() for job in jobs]
        else:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                done = dict(zip(order, pool.map(lambda i: jobs[i](), order), strict=True))
            results = [done[i] for i in range(len(jobs))]
        self.timing = dict(zip(("rollout_s", "score_s"), np.sum([s for *_, s in results], axis=0).tolist(),
                               strict=True))
        if own and len(candidates) > 1 and any(np.all(np.isnan(total)) for total, *_ in results):
            # a row diverged and took its batch's rows with it: each alone, so only it is lost
            _LOG.info("scoring the %d rows one at a time", len(candidates))
            return self._losses(candidates, velocity, frames, False, None, False)
        return (np.concatenate([total for total, *_ in results]),
                np.concatenate([per for _, per, _ in results]))

    def _together(self, together: bool | None, substeps: int | None, own: bool) -> bool:
        """Whether ``_losses`` scores its rows in batches rather than each alone at its own time step."""
        if own:
            return True
        if together is None:
            return self.identifier.sim.device.startswith("cuda") or substeps is not None
        return together

    def _costliest_first(self, candidates: np.ndarray) -> list[int]:
        """The rows of ``candidates`` by their substeps per frame, the most first (ties in order)."""
        probe = self.simulator(1)
        substeps = []
        for row in candidates:
            self.configure(probe, row[None])
            substeps.append(probe.time_step()[0])
        return sorted(range(len(candidates)), key=lambda i: -substeps[i])

    def simulator(self, n: int, slot: int = 0) -> Simulator:
        """The kept simulator of ``n`` batched rows for worker ``slot`` (made on first use)."""
        key = (n, slot)
        if key not in self.simulators:
            problem = self.identifier.problem
            self.simulators[key] = Simulator(problem.objects, problem.particles, problem.sim_config,
                                             n_batch=n)
        return self.simulators[key]

    def configure(self, batch: Simulator, candidates: np.ndarray) -> np.ndarray:
        """Set ``batch`` to the rows ``candidates``; (B, N) which particles are inside the surface.

        What no entry sets comes from the identifier's own simulator, as ``Identifier.apply``
        left it.
        """
        fit = self.identifier
        n = len(candidates)
        batch.set_initial_velocity(fit.sim.initial_velocity()[0])
        rows = {}
        for name in dict.fromkeys(e.name for e in fit.entries if e.name != OFFSET):
            values = rows[name] = np.repeat(fit.sim.params.get(name), n, axis=0)
            for i, entry in enumerate(fit.entries):
                if entry.name == name:
                    values[(slice(None),) + entry.index[1:]] = entry.coordinate.to_theta(candidates[:, i])
        batch.params.update(rows)
        offsets = fit.offsets_of(candidates)
        boundary = fit.problem.boundary
        if boundary is None:
            return np.ones((n, len(fit.index)), dtype=bool)
        batch.set_volume(np.stack([boundary.volumes(o[fit.index]) for o in offsets]))
        return np.stack([boundary.inside(o[fit.index]) for o in offsets])

    def _score(self, batch: Simulator, inside: np.ndarray, frames: int, substeps: int | None = None,
               own: bool = False) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
        """Roll the configured ``batch`` out over ``frames`` frames and score each row.

        ``own``: each row at its own time step. Returns the rows' losses, their per-object shares
        and (rollout, scoring) seconds. On a GPU the scores are queued behind the rollout
        (``Simulator.queue_rollout``), and the host reads them once it has waited for both.
        """
        fit = self.identifier
        obs = fit.problem.observations
        n = batch.n_batch
        tick = time.perf_counter()
        try:
            if fit.tensor_device is not None:  # scored behind the rollout on the device, then waited for
                queued = batch.queue_rollout(frames, substeps=substeps, own_steps=own)
                scores = self._tensor_scores(queued_positions(queued.positions, n, batch.n_particles,
                                                              fit.tensor_device), inside, frames)
                queued.wait()
            else:
                traj = batch.rollout(frames, substeps=substeps, own_steps=own)
        except SimulationDiverged as error:
            _LOG.warning("a rollout diverged (%s); its candidates are left out", error)
            return np.full(n, np.nan), np.full((n, obs.n_objects), np.nan), (time.perf_counter() - tick, 0.0)
        rolled = time.perf_counter()
        if fit.tensor_device is not None:
            total, per = (value.cpu().numpy() for value in scores)
        else:
            total, per = self._frame_scores(traj, inside, frames)
        return total, per, (rolled - tick, time.perf_counter() - rolled)

    def _frame_scores(self, traj: np.ndarray, inside: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
        """The losses (B,) and their per-object shares (B, K) of the rows of rollout ``traj``.

        On the CPU: the Chamfer and track terms of each row and frame in threads (KD-tree
        queries release the GIL), the silhouettes row by row.
        """
        fit = self.identifier
        obs, s = fit.problem.observations, fit.settings
        n = traj.shape[1]

        def frame_loss(job: tuple[int, int]) -> tuple[float, np.ndarray]:
            b, f = job
            value, _, per = geometry_loss(traj[f, b, inside[b]].astype(np.float64),
                                          fit.index[inside[b]], obs.points[f],
                                          s.loss.per_object, obs.trees(f))
            value, per = s.loss.chamfer_weight * value, s.loss.chamfer_weight * per
            if s.loss.track_weight > 0 and obs.tracks is not None:  # as Identifier.window_loss
                tracked, _, shares = track_loss(traj[f, b].astype(np.float64), obs.tracks, f,
                                                s.loss.track_scale, obs.n_objects)
                value, per = value + s.loss.track_weight * tracked, per + s.loss.track_weight * shares
            return value, per

        jobs = [(b, f) for b in range(n) for f in range(1, frames + 1)]
        with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
            scored = list(pool.map(frame_loss, jobs))
        total = np.array([value for value, _ in scored]).reshape(n, frames).mean(axis=1)
        per = np.stack([per for _, per in scored]).reshape(n, frames, -1).mean(axis=1)
        if s.loss.silhouette_weight > 0 and obs.masks:
            for b in range(n):  # as Identifier.window_loss: the particles inside the surface
                silhouette = s.loss.silhouette_weight / frames * silhouette_object_losses(
                    traj[1:frames + 1, b][:, inside[b]], fit.index[inside[b]], obs.object_ids,
                    obs.views, obs.masks[1:frames + 1], fit.splat_radius, s.loss.per_object,
                    fit.torch_device)
                total[b] += silhouette.sum()
                per[b] += silhouette  # NaN stays NaN: the scene-level loss has no shares
        return total, per

    def _tensor_scores(self, x: torch.Tensor, inside: np.ndarray, frames: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``_frame_scores`` of every row and frame at once, as tensors on ``tensor_device``.

        ``x`` (B, F, N, 3) float64 the rows' particles at frames 1..``frames`` there; nothing here
        waits for the device (``tensor_terms``).
        """
        fit = self.identifier
        obs, loss, device = fit.problem.observations, fit.settings.loss, fit.tensor_device
        with torch_threads(device), torch.no_grad():
            terms = tensor_terms(x, inside, fit.index, obs.tensors(device),
                                 obs.object_ids, slice(1, frames + 1), loss, fit.splat_radius)
            shares = loss.silhouette_weight / frames * terms.silhouette
            total = ((loss.chamfer_weight * terms.chamfer_total + loss.track_weight * terms.track.sum(dim=2))
                     .mean(dim=1) + shares.sum(dim=1))
            per = (loss.chamfer_weight * terms.chamfer + loss.track_weight * terms.track).mean(dim=1) + shares
        return total, per

    def box(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper coordinates the first round samples around ``u`` (module docstring)."""
        fit = self.identifier
        lo, hi = np.empty(len(u)), np.empty(len(u))
        for i, entry in enumerate(fit.entries):
            if entry.name in SEARCH_RANGES:
                ends = [float(entry.coordinate.to_u(v)) for v in SEARCH_RANGES[entry.name]]
                lo[i], hi[i] = min(ends), max(ends)
            else:
                half = (fit.settings.search_decades * np.log(10.0)
                        if entry.coordinate.kind == "log" else 2.0)
                lo[i], hi[i] = u[i] - half, u[i] + half
        return lo, hi

    def best(self, current: np.ndarray, candidates: np.ndarray, velocity: np.ndarray,
             groups: list[list[int]], keep: int = 1,
             current_loss: float | None = None) -> list[tuple[np.ndarray, float]]:
        """The ``keep`` best of ``current``, ``candidates`` and their per-object composite.

        ``groups[k]``: the coordinates (columns) object k's loss chooses. The candidates are
        scored as ``batch_object_losses`` does by default (on a GPU in one batch, at the time
        step of its stiffest row); the contenders (``current``, the composite and the ``keep``
        best candidates) are then compared each at its own time step, as the gradient fit will
        see them (the loss of one parameter set differs by up to 10 % between time steps, more
        than a search step gains). Only those not scored so already are rolled out again:
        ``current`` when ``current_loss`` (its loss) is given, and on the CPU, whose batch scores
        each candidate alone at its own step, the best candidates (a rollout repeats to the bit
        on the CPU, and scoring each row is independent of the others). Best first, as (u, loss);
        empty if every candidate diverged.
        """
        return self.best_of([(current, candidates, current_loss)], velocity, groups, keep)[0]

    def best_of(self, rounds: list[tuple[np.ndarray, np.ndarray, float | None]], velocity: np.ndarray,
                groups: list[list[int]], keep: int = 1) -> list[list[tuple[np.ndarray, float]]]:
        """``best`` of each of several rounds (current, candidates, current_loss), side by side.

        Each round's candidates are scored in a batch of their own, and the contenders of all
        rounds together: on a GPU a batch of a few rows costs what its stiffest row's launches
        do, so the rounds of the search's starts share one.
        """
        s = self.identifier.settings
        alone = not self._together(None, None, False)
        pending: list[tuple[list[np.ndarray], list[float | None]]] = []
        for current, candidates, current_loss in rounds:
            total, per = self.batch_object_losses(candidates, velocity, s.search.frames)
            if np.all(np.isnan(total)):
                pending.append(([], []))
                continue
            top = [i for i in np.argsort(total)[:keep] if not np.isnan(total[i])]
            composite = candidates[top[0]].copy()
            if not np.all(np.isnan(per)):
                for k, columns in enumerate(groups):
                    if columns and not np.all(np.isnan(per[:, k])):
                        composite[columns] = candidates[int(np.nanargmin(per[:, k])), columns]
            contenders, losses = [current], [current_loss]
            for u, loss in [(composite, None), *((candidates[i], total[i] if alone else None) for i in top)]:
                same = next((j for j, c in enumerate(contenders) if np.allclose(u, c)), None)
                if same is None:
                    contenders.append(u)
                    losses.append(loss)
                elif losses[same] is None and np.array_equal(u, contenders[same]):
                    losses[same] = loss
            if len(contenders) == 1:  # nothing to compare: the batch's best loss goes with it
                losses = [float(np.nanmin(total))]
            pending.append((contenders, losses))
        missing = [(r, i) for r, (_, losses) in enumerate(pending) for i, loss in enumerate(losses) if loss is None]
        if missing:
            scored = self.batch_object_losses(np.array([pending[r][0][i] for r, i in missing]), velocity,
                                              s.search.frames, together=False)[0]
            for (r, i), loss in zip(missing, scored, strict=True):
                pending[r][1][i] = loss
        found = []
        for contenders, losses in pending:
            values = np.array(losses, dtype=np.float64)
            order = [i for i in np.argsort(values) if not np.isnan(values[i])]
            found.append([(contenders[i].copy(), float(values[i])) for i in order[:keep]])
        return found

    def run(self, velocity: np.ndarray, checkpoint: Checkpoint | None = None) -> list[tuple[np.ndarray, float]]:
        """Latin-hypercube rounds in ever narrower boxes (module docstring); the ends, the best applied.

        Returns each start's end as (u, loss), the lowest loss first; without samples, the
        identifier's own point with a NaN loss.

        The starts' later rounds run side by side (``best_of``): round r of every start, then
        round r + 1. Their samples are drawn, after the first round's, as if the starts ran one
        after another.

        With ``checkpoint``, each finished round is saved (the points it kept with their losses;
        for the first, the sampler's state after it), and the rounds a stopped run of the same
        fit finished are taken from there instead of being scored again: the search ends where
        an uninterrupted one does.
        """
        fit = self.identifier
        s = fit.settings
        u = fit.pack()
        lo, hi = self.box(u)
        n_objects = len(fit.problem.objects)
        per_object = [[i for i, e in enumerate(fit.entries) if e.per_object and e.index[1] == k]
                      for k in range(n_objects)]
        rng = np.random.default_rng(0)
        ranged = np.array([e.name in SEARCH_RANGES for e in fit.entries])
        finished = checkpoint.load_search() if checkpoint is not None else []
        # a later round's entry holds a list of kept points per start ("starts")
        finished = finished[:1] + list(itertools.takewhile(lambda done: "starts" in done, finished[1:]))
        if finished:
            _LOG.info("resuming the search from %s: %d rounds done", checkpoint.directory, len(finished))
        rounds_done: list[dict] = []

        def kept(values: list) -> list[tuple[np.ndarray, float]]:  # from the checkpoint's JSON
            return [(np.array(u, dtype=np.float64), float(value)) for u, value in values]

        def listed(points: list[tuple[np.ndarray, float]]) -> list:  # to it
            return [(u.tolist(), value) for u, value in points]

        def saved(entry: dict) -> None:
            rounds_done.append(entry)
            if checkpoint is not None:
                checkpoint.save_search(rounds_done)

        def unit() -> np.ndarray:
            # Latin hypercube: every coordinate's range cut into as many strata as samples,
            # one sample per stratum, strata paired at random across coordinates
            strata = np.stack([rng.permutation(s.search.samples) for _ in u], axis=1)
            return (strata + rng.random(strata.shape)) / s.search.samples

        def samples(centre: np.ndarray, number: int, draw: np.ndarray) -> np.ndarray:
            half = 0.5 * (hi - lo) / 3.0**number
            box_lo, box_hi = (lo, hi) if number == 0 else (centre - half, centre + half)
            box_lo = np.where(ranged, np.maximum(box_lo, lo), box_lo)
            box_hi = np.where(ranged, np.minimum(box_hi, hi), box_hi)
            return box_lo + (box_hi - box_lo) * draw

        restored = 0  # rounds of one start's samples that the checkpoint holds

        def searched(done: int) -> None:  # rounds of one start's samples scored, of ``rounds``
            if done < restored:  # a resumed search reports from where it stopped
                return
            fit.report({"phase": "search", "done": done * s.search.samples,
                        "total": rounds * s.search.samples})

        ends: list[tuple[np.ndarray, float]] = []  # each start's (u, loss)
        if s.search.samples > 0:
            rounds = 1 + max(1, s.search.starts) * s.search.rounds  # fewer if starts diverge
            restored = 1 if finished else 0
            searched(0)
            # the first round's best points are the starts: each narrows on its own basin
            if finished:
                rng.bit_generator.state = finished[0]["sampler"]
                rounds_done.append(finished[0])
                ends = kept(finished[0]["kept"])
            else:
                ends = self.best(u, samples(u, 0, unit()), velocity, per_object, max(1, s.search.starts))
                saved({"kept": listed(ends), "sampler": rng.bit_generator.state})
            n = len(ends)
            rounds = 1 + n * s.search.rounds
            restored = 1 + (len(finished) - 1) * n if finished else 0
            searched(1)
            draws = [[unit() for _ in range(s.search.rounds)] for _ in ends]
            for number in range(1, s.search.rounds + 1 if ends else 1):  # no starts: every sample diverged
                if len(rounds_done) < len(finished):  # finished before the stop
                    entry = finished[len(rounds_done)]
                    rounds_done.append(entry)
                    found = [kept(values) for values in entry["starts"]]
                else:
                    found = self.best_of([(start, samples(start, number, draws[k][number - 1]), loss)
                                          for k, (start, loss) in enumerate(ends)], velocity, per_object)
                    saved({"starts": [listed(f) for f in found]})
                ends = [f[0] if f else end for f, end in zip(found, ends, strict=True)]
                for k in range(n):
                    searched(1 + (number - 1) * n + k + 1)
            for k, (start, loss) in enumerate(ends):
                _LOG.info("search start %d of %d: loss %.3g: %s", k + 1, n, loss, fit.values_of(start))
        ends = sorted(ends, key=lambda end: end[1]) if ends else [(u, math.nan)]
        fit.apply(ends[0][0], velocity)
        return ends
