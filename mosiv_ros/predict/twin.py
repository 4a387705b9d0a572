"""The digital twin: the identified scene rolled forward, for planners and for evaluation.

``Twin`` holds the lifted particles of the first observed frame, the identified parameters
(``identify.estimates.Estimates``: material parameters, initial velocities, ground and effect
parameters), the scene declaration and the declared gripper's poses (``gripper_poses``: the
recorded ones, held at the last past it), and simulates from that first frame through the
observed window and on past it. Requests can change the initial velocities or any object's parameters
(swapped materials) before the rollout (``what_if``, with a ``request.WhatIf``).

What it is for: ``Twin.predict(seconds)`` -> ``Prediction`` (per-frame particle positions and
centroid paths, with times). What it is not for: fitting, or ROS messages (``nodes``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mosiv_ros.identify.estimates import Estimates
from mosiv_ros.io.recording import PointCloud
from mosiv_ros.io.scene import Scene
from mosiv_ros.lifting.lift import LiftedParticles
from mosiv_ros.predict.request import WhatIf
from mosiv_ros.sim import WALL_RETRIES, ObjectModel, SimConfig, Simulator, domain_around, reaches_walls
from mosiv_ros.simulation import OFFSET, colliders_of, effects_of, ground_of, to_sim_particles

_LOG = logging.getLogger(__name__)

PREDICTION_MARGIN = 0.25
"""Metres of free space around the objects' first positions that a prediction starts with (an
empty grid node still costs each substep); a rollout whose objects go further is run again on a
domain around where they went, with twice the margin (``reaches_walls``)."""


@dataclass
class Prediction:
    """Predicted particle positions (F, N, 3) at ``times`` (F,) seconds after ``start_ns``.

    The particles are those inside each object's estimated surface (the boundary band of the
    simulation is left out).
    """

    start_ns: int
    times: np.ndarray
    positions: np.ndarray
    object_index: np.ndarray
    object_ids: list[int]
    names: list[str]
    rgb: np.ndarray | None = None
    """(N, 3) uint8: each particle's lifted colour, for re-rendering (None: not known)."""

    def centroids(self) -> np.ndarray:
        """(F, K, 3) centroid of each object per predicted frame."""
        return np.stack([self.positions[:, self.object_index == k].mean(axis=1)
                         for k in range(len(self.object_ids))], axis=1)

    def after(self, seconds: float, frame_rate: float | None = None) -> Prediction:
        """The frames at or after ``seconds`` (e.g. past the observed window).

        With ``frame_rate``, thinned to about that many frames per second.
        """
        keep = np.flatnonzero(self.times >= seconds - 1e-9)
        if frame_rate and len(self.times) > 1:
            step = max(1, int(round(1.0 / (frame_rate * (self.times[1] - self.times[0])))))
            keep = keep[::step]
        return Prediction(self.start_ns, self.times[keep], self.positions[keep],
                          self.object_index, self.object_ids, self.names, self.rgb)

    def stamps_ns(self) -> list[int]:
        """Absolute stamp of every frame."""
        return [self.start_ns + int(round(t * 1e9)) for t in self.times]

    def to_cloud(self, stamp_ns: int) -> PointCloud:
        """Every frame in one cloud with a field ``t``: seconds after ``stamp_ns``."""
        n_frames, n = self.positions.shape[:2]
        t = (self.start_ns + np.repeat(self.times, n) * 1e9 - stamp_ns) * 1e-9
        ids = np.asarray(self.object_ids, dtype=np.uint16)[np.tile(self.object_index, n_frames)]
        return PointCloud(self.positions.reshape(-1, 3), ids, {"t": t.astype(np.float32)},
                          stamp_ns=stamp_ns)


class Twin:
    """The identified scene, ready to roll forward (see the module docstring)."""

    def __init__(self, lifted: LiftedParticles, estimates: Estimates, scene: Scene,
                 device: str = "auto", margin: float = PREDICTION_MARGIN,
                 gripper_poses: Sequence[tuple[int, np.ndarray]] = ()) -> None:
        self.lifted, self.estimates = lifted, estimates
        self.colliders = colliders_of(scene, gripper_poses, estimates.stamp_ns)
        by_id = {o.id: o for o in estimates.objects}
        offsets = {i: o.params[OFFSET] for i, o in by_id.items() if OFFSET in o.params}
        particles, ids = to_sim_particles(lifted, offsets)
        missing = [i for i in ids if i not in by_id]
        if missing:
            raise ValueError(f"no estimate for object id(s) {missing} (estimated: {sorted(by_id)})")
        self.ids = ids
        self.objects = [ObjectModel(by_id[i].name, by_id[i].family,
                                    {k: v for k, v in by_id[i].params.items() if k != OFFSET}, id=i)
                        for i in ids]
        self.scene, self.device, self.margin = scene, device, margin
        self.particles = particles
        self.sim = self._simulator(particles.x)
        self.sim.params.update({k: v for k, v in estimates.scene.items() if k in self.sim.params})
        # what a prediction reports: the solid, not the boundary band (volume ~0, up to the band's
        # width outside the surface) that the simulation carries for the M-PhyGs volumes
        solid = lifted.solid(offsets)
        for k in range(len(ids)):  # an object too thin to have a particle inside keeps them all
            mine = particles.object_index == k
            if not solid[mine].any():
                solid[mine] = True
        self.solid = solid
        self.rgb = lifted.rgb[solid] if lifted.rgb is not None else None
        self.velocity = np.array([by_id[i].velocity for i in ids], dtype=np.float64)

    @property
    def window_seconds(self) -> float:
        """Length of the observed window the estimates were fitted on."""
        return max(self.estimates.frames - 1, 0) * self.estimates.frame_dt

    def future(self, horizon: float, frame_rate: float, progress=None) -> Prediction:
        """The predicted frames from the end of the observed window to ``horizon`` s past it."""
        whole = self.predict(self.window_seconds + horizon, progress=progress)
        return whole.after(self.window_seconds, frame_rate)

    def predict(self, seconds: float, velocity: np.ndarray | None = None,
                params: Mapping[str, Mapping[str, float]] | None = None,
                progress=None) -> Prediction:
        """Roll out ``seconds`` from the first observed frame.

        ``velocity`` (K, 6) replaces the identified initial velocities (new initial conditions);
        ``params`` {object name: {parameter: value}} replaces identified parameters (swapped
        materials).
        """
        velocity = self.velocity if velocity is None else np.asarray(velocity, dtype=np.float64)
        changed = {key for values in (params or {}).values() for key in values}
        identified = {key: self.sim.params.get(key) for key in changed}
        try:
            for name, values in (params or {}).items():
                for key, value in values.items():
                    self.sim.params.set(key, {name: value})
            return self._rollout(seconds, velocity, progress)
        finally:  # a request changes this prediction only
            for key, value in identified.items():
                self.sim.params.set(key, value)

    def what_if(self, request: WhatIf, horizon: float, frame_rate: float, progress=None) -> Prediction:
        """A what-if prediction: the request's initial velocities and parameters, rolled out.

        Every frame from the first observed one to ``horizon`` s past the window. ValueError if
        the request names an unknown object, or a parameter its family lacks or out of range.
        """
        request.check({o.name: o.family for o in self.objects})
        velocity = request.velocity(self.velocity, [o.name for o in self.objects])
        whole = self.predict(self.window_seconds + horizon, velocity, request.params, progress)
        return whole.after(0.0, frame_rate)

    def _simulator(self, points: np.ndarray) -> Simulator:
        """The twin's simulator on a domain ``self.margin`` around ``points`` and the floor."""
        ground = ground_of(self.scene)
        dx = 2.0 * self.lifted.lattice_volume ** (1 / 3)
        lo, hi = domain_around(points, dx, self.margin, floor=ground.height if ground else None)
        self.config = SimConfig(dx=dx, lo=lo, hi=hi, frame_dt=self.estimates.frame_dt or 1 / 30,
                                ground=ground, effects=effects_of(self.scene, self.objects),
                                colliders=self.colliders, device=self.device)
        return Simulator(self.objects, self.particles, self.config)

    def _widen(self, visited: np.ndarray) -> None:
        """A simulator on a domain around ``visited`` with twice the margin, the parameters kept."""
        self.margin *= 2
        wider = self._simulator(np.concatenate([self.particles.x, visited.reshape(-1, 3)]))
        for name in self.sim.params.specs:
            wider.params.set(name, self.sim.params.get(name))
        self.sim = wider

    def _rollout(self, seconds: float, velocity: np.ndarray, progress) -> Prediction:
        index = self.particles.object_index
        centre = np.stack([self.particles.x[index == k].mean(axis=0) for k in range(len(self.ids))])
        v = velocity[index, :3] + np.cross(velocity[index, 3:], self.particles.x - centre[index])
        n_frames = max(1, math.ceil(seconds / self.config.frame_dt - 1e-9))
        for attempt in range(WALL_RETRIES + 1):
            self.sim.set_initial_velocity(v)
            positions = self.sim.rollout(n_frames, progress=progress)[:, 0]
            if not reaches_walls(positions, self.sim.lo, self.sim.hi, self.config.dx):
                break
            if attempt == WALL_RETRIES:
                _LOG.warning("prediction: the objects still reach the walls of a domain %s m wide after %d "
                             "widenings; past there the walls, not the scene, stop them",
                             np.round(self.sim.hi - self.sim.lo, 2).tolist(), WALL_RETRIES)
                break
            _LOG.info("prediction: the objects reached the domain's walls; widening it to where they went "
                      "and rolling out again")
            self._widen(positions)
        positions = positions[:, self.solid]
        return Prediction(self.estimates.stamp_ns, np.arange(n_frames + 1) * self.config.frame_dt,
                          positions.astype(np.float64), index[self.solid], list(self.ids),
                          [o.name for o in self.objects], self.rgb)
