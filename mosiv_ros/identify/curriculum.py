"""The gradient fit: Adam over a horizon curriculum of windows, resynchronised (MOSIV stage 3).

``Curriculum(identifier).run(state, saved)`` takes a ``FitState`` (the point Adam starts from,
or where an interrupted fit stopped) through the curriculum stages ``settings.curriculum.horizons``:

- horizon curriculum (M-PhyGs temporal mini-batches, MOSIV horizon curriculum): stage h fits
  windows of h frames, up to ``curriculum.windows`` of them spread over the sequence and taken in turn
  (``window_starts``); the last stage (0) fits the whole sequence from frame 0;
- resynchronisation (MOSIV): a window that starts at frame s > 0 starts from the state of an
  anchor rollout with the current parameters at s, each object's particles shifted (and their
  velocities offset) so that its centroid position and velocity match the observations at s
  (``resynced``), which stops drift from one window leaking into the next. The anchor is
  refreshed every ``resync_every`` iterations;
- Adam's steps are projected back into each coordinate's range (``Identifier.project``);
- a diverging rollout (a window's or the anchor's) does not end the fit: the step is undone
  and the learning rate halved (``retreat``);
- every whole-window iteration's loss is compared: ``FitState.best`` keeps the lowest;
- ``race(states)`` runs the first stage from each of several points (the search's ends whose
  losses lie too close to rank them) and names the one that fits best there, to go on; on a
  GPU the points run in step, as the rows of one batched rollout each at its own time step.

``saved(state)`` is called after every iteration (the checkpoint). The identifier
(``identify.fit.Identifier``) supplies the problem, the settings and the loss of a window.

What it is for: the gradient steps. What it is not for: the search before them
(``identify.search``), choosing the result among the points reached (``Identifier.run``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from mosiv_ros.sim import SimState, Simulator
from mosiv_ros.sim.errors import SimulationDiverged

if TYPE_CHECKING:
    from mosiv_ros.identify.fit import Identifier

_LOG = logging.getLogger(__name__)


class Adam:
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


def _no_point() -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    return math.inf, np.zeros(0), np.zeros(0), np.zeros(0)


@dataclass
class FitState:
    """Where a gradient fit is: what a checkpoint holds.

    ``u`` and ``velocity`` (K, 6) the current point, ``start`` (u, velocity) the point Adam
    started from (the search's), ``best`` the lowest whole-window loss an iteration saw as
    (loss, u, velocity, per-object losses), ``history`` a record per iteration, ``stage`` and
    ``iteration`` the next iteration to run, ``failures`` the diverged iterations so far.
    """

    u: np.ndarray
    velocity: np.ndarray
    adam: Adam
    start: tuple[np.ndarray, np.ndarray]
    best: tuple[float, np.ndarray, np.ndarray, np.ndarray] = field(default_factory=_no_point)
    history: list[dict] = field(default_factory=list)
    stage: int = 0
    iteration: int = 0
    failures: int = 0


def window_starts(n: int, length: int, windows: int) -> list[int]:
    """First frames of a stage's windows of ``length`` frames of ``n``: at most ``windows``, spread."""
    if length == n:
        return [0]
    return sorted({int(round(x)) for x in np.linspace(0, n - length, min(windows, n - length + 1))})


class Curriculum:
    """The gradient fit of ``identifier``'s problem; see the module docstring."""

    def __init__(self, identifier: Identifier) -> None:
        self.identifier = identifier

    def stages(self) -> list[int]:
        """Each stage's window length in frames (the whole sequence for 0 or longer)."""
        n = self.identifier.problem.observations.n_frames - 1
        return [h if 0 < h < n else n for h in self.identifier.settings.curriculum.horizons]

    def run(self, state: FitState, saved: Callable[[FitState], None], until: int | None = None,
            before: int = 0, raced: int = 0) -> FitState:
        """Iterate from ``state`` to the curriculum's end, or to stage ``until``'s start.

        ``saved(state)`` after every iteration. The progress records count ``before`` iterations
        ahead of this state's own, and ``raced`` more in the total: the race's (``race``).
        """
        return self._run([state], saved, until, before, raced)[0]

    def _run(self, states: list[FitState], saved: Callable[[FitState], None], until: int | None,
             before: int, raced: int) -> list[FitState]:
        """``run`` of several states in step, all at one stage and iteration (``race``).

        One state runs on the identifier's simulator. Several run as the rows of one batched
        rollout, each at its own time step, and get what each would alone (``Simulator.rollout``
        with ``own_steps``); their iterations are counted in turn in the progress. Should a
        batched rollout diverge, the rows cannot tell whose step to undo: each state then goes
        on alone from where they all are.
        """
        fit, s = self.identifier, self.identifier.settings
        n = fit.problem.observations.n_frames - 1
        together = len(states) > 1
        moving = [np.linalg.norm(state.velocity[:, :3], axis=1) > 0 for state in states]
        stages = self.stages()
        stage0, iteration0 = states[0].stage, states[0].iteration
        for stage in range(stage0, len(stages) if until is None else min(until, len(stages))):
            length = stages[stage]
            starts = window_starts(n, length, s.curriculum.windows)
            anchor: dict[int, SimState] = {}
            for iteration in range(iteration0 if stage == stage0 else 0, s.curriculum.iterations):
                tick = time.perf_counter()
                points = [(state.u, state.velocity) for state in states]
                if together:
                    sim, inside = fit.rows(points)
                else:
                    fit.apply(*points[0])
                    sim = fit.sim
                start = starts[iteration % len(starts)]
                try:
                    if start > 0 and (start not in anchor or iteration % s.resync_every == 0):
                        anchor = {}  # a diverging anchor rollout leaves none to reuse
                        anchor = self.anchor(starts, sim, own_steps=together)
                    initial = self.resynced(anchor, start) if start > 0 else None
                    if together:
                        u = np.stack([u for u, _ in points])
                        results = fit.window_losses(sim, u, fit.offsets_of(u), inside, start, length, initial,
                                                    grad=True, own_steps=True)
                    else:
                        results = [fit.window_loss(start, length, initial, grad=True)]
                except SimulationDiverged as error:
                    if together:
                        _LOG.warning("a batched iteration diverged (%s); the %d states go on one after another",
                                     error, len(states))
                        # counted on from the iterations done in step, the states' rest one after another
                        done, left = before + iteration * len(states), s.curriculum.iterations - iteration
                        return [self._run([state], saved, until, done + r * left - iteration, raced)[0]
                                for r, state in enumerate(states)]
                    state = states[0]
                    state.failures += 1
                    state.adam.lr *= 0.5
                    state.u, state.velocity, back = self.retreat(state)
                    _LOG.warning("iteration %d diverged (%s); %s, learning rates halved",
                                 iteration, error, back)
                    continue
                substeps = sim.own_time_steps()[0] if together else [sim.time_step()[0]]
                share = {"seconds": time.perf_counter() - tick, **fit.timing}
                share = {key: value / len(states) for key, value in share.items()}
                for r, (state, (loss, du, dv, per)) in enumerate(zip(states, results, strict=True)):
                    u, velocity = state.u, state.velocity
                    if start == 0 and length == n and loss < state.best[0]:
                        state.best = (loss, u.copy(), velocity.copy(), per.copy())
                    if not s.fit_velocity:
                        dv[:] = 0.0
                    dv[~moving[r]] = 0.0  # an object found at rest stays at rest at t = 0
                    step = state.adam.step(np.concatenate([du, dv.ravel()]))
                    moved = fit.project(u + step[: len(u)])
                    state.adam.last[: len(u)] = moved - u  # the step taken, for an undo
                    state.u, state.velocity = moved, velocity + step[len(u):].reshape(velocity.shape)
                    record = {"stage": stage, "window": length, "start": start, "iteration": iteration,
                              "loss": loss, "values": fit.values_of(state.u), "substeps": int(substeps[r]),
                              **share}
                    if together:
                        record["rows"] = len(states)
                    state.history.append(record)
                    done = before + (stage * s.curriculum.iterations + iteration) * len(states) + r + 1
                    fit.report({"phase": "fit", "done": done,
                                "total": raced + len(stages) * s.curriculum.iterations, **record})
                    state.stage, state.iteration = stage, iteration + 1
                    saved(state)
        return states

    def race(self, states: list[FitState]) -> tuple[int, list[float]]:
        """The first stage from each of ``states`` (the search's closest ends); which goes on, and the scores.

        A state's score is its mean loss over the stage's last pass over its windows: the same
        windows for every state, an iteration's loss that of the point the step before reached;
        infinite if an iteration of that pass diverged. The lowest goes on; the states are left
        at the stage's end. Where the search batches rows at their own time steps (on a GPU,
        ``GlobalSearch.own_step_batches``) and the scene allows it, the states run in step as
        the rows of one rollout, which costs about what the stiffest alone does; else one after
        another. The progress records count every state's iterations, and the curriculum's
        after them (``run``'s ``raced``: ``raced(len(states))``).
        """
        fit, s = self.identifier, self.identifier.settings
        iterations = s.curriculum.iterations
        n = fit.problem.observations.n_frames - 1
        last_pass = min(iterations, len(window_starts(n, self.stages()[0], s.curriculum.windows)))
        if fit.search.own_step_batches and fit.sim.own_steps_allowed:
            self._run(states, lambda _: None, 1, 0, self.raced(len(states)))
        else:
            for r, state in enumerate(states):
                self.run(state, lambda _: None, until=1, before=r * iterations, raced=self.raced(len(states)))
        scores = []
        for state in states:
            losses = [h["loss"] for h in state.history if h["iteration"] >= iterations - last_pass]
            scores.append(float(np.mean(losses)) if len(losses) == last_pass else math.inf)
        return int(np.argmin(scores)), scores

    def raced(self, ends: int) -> int:
        """Iterations a race of ``ends`` adds to the curriculum's (none for one end)."""
        return max(ends - 1, 0) * self.identifier.settings.curriculum.iterations

    def retreat(self, state: FitState) -> tuple[np.ndarray, np.ndarray, str]:
        """Where to go after a diverged iteration: (u, velocity, what was done).

        Adam's last step is undone; if there is none (the point passed one window and diverged
        on another, or a step was undone already), back to the lowest whole-window point seen,
        else the search's: undoing nothing would try the same point again and again.
        """
        u, velocity = state.u, state.velocity
        if state.adam.last.any():
            return (*state.adam.undo(u, velocity), "step undone")
        points = [("the best whole-window point", *state.best[1:3])] if math.isfinite(state.best[0]) else []
        points.append(("the search's point", *state.start))
        for label, point_u, point_velocity in points:
            if len(point_u) and not np.array_equal(point_u, u):
                return point_u.copy(), point_velocity.copy(), f"back to {label}"
        return u, velocity, "nothing to undo"

    def resynced(self, anchor: dict[int, SimState], start: int) -> SimState:
        """The anchor state at ``start`` with each object's centroid moved onto the observed one (in every row)."""
        fit = self.identifier
        state = anchor[start]
        x, v = state.x.copy(), state.v.copy()
        c_obs = fit.observed_centroids
        dt = fit.problem.observations.frame_dt
        for row in range(len(x)):
            for k in range(fit.problem.observations.n_objects):
                mine = fit.index == k
                if np.isnan(c_obs[start, k, 0]):
                    continue
                x[row, mine] += c_obs[start, k] - x[row, mine].mean(axis=0)
                # central difference: a forward one lags by half a frame of acceleration
                before, after = c_obs[start - 1, k], c_obs[min(start + 1, len(c_obs) - 1), k]
                if start + 1 < len(c_obs) and not (np.isnan(before[0]) or np.isnan(after[0])):
                    v[row, mine] += (after - before) / (2 * dt) - v[row, mine].mean(axis=0)
        return SimState(x, v, state.C, state.b)

    def anchor(self, starts: list[int], sim: Simulator | None = None,
               own_steps: bool = False) -> dict[int, SimState]:
        """``sim``'s states (the identifier's by default) at ``starts`` > 0, from one rollout with its parameters.

        ``own_steps``: each row at its own time step, as the windows from them run.
        """
        last = max(starts)
        if last == 0:
            return {}
        sim = sim or self.identifier.sim
        sim.rollout(last, grad=True, own_steps=own_steps)
        return {s: sim.frame_state(s) for s in starts if s > 0}
