"""Lifted particles as the simulator's input, for given boundary offsets.

What it is for: ``to_sim_particles`` builds ``mosiv_ros.sim.Particles`` (positions, volumes,
object index 0..K-1) from ``LiftedParticles``, with M-PhyGs volumes for the offsets o_s the
identifier is trying. Kept apart from ``lift`` so that lifting does not load the simulator.
What it is not for: lifting itself or choosing the offsets.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from mosiv_ros.lifting.lift import LiftedParticles
from mosiv_ros.sim import Particles


def to_sim_particles(lifted: LiftedParticles,
                     offsets: Mapping[int, float] | None = None) -> tuple[Particles, list[int]]:
    """(Particles, object ids) for the simulator, with boundary offsets o_s per segment.

    A particle's object index is its id's position in the returned list (ids in increasing
    order); volumes are V_i = V_g (sigmoid(-beta (d_i + o_s)) + eps).
    """
    ids = lifted.object_ids
    index = np.searchsorted(np.asarray(ids), lifted.object_id)
    return Particles(lifted.x, lifted.volumes(offsets), index), ids
