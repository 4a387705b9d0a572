"""Stage 2, lifting an observed frame into per-object simulation particles (no ROS here).

``lift`` / ``lift_first_complete`` (``lift``) give ``LiftedParticles``: non-overlapping per-object
particles with signed distances, M-PhyGs boundary volumes, object ids, segments and material
families; ``density`` holds the grid steps. ``mosiv_ros.simulation`` gives the particles to the
simulator.
"""

from mosiv_ros.lifting.lift import (
    UNKNOWN_MATERIAL,
    LiftedParticles,
    border_note,
    boundary_volume,
    lift,
    lift_choice,
    lift_first_complete,
    missing_objects,
)

__all__ = ["UNKNOWN_MATERIAL", "LiftedParticles", "border_note", "boundary_volume", "lift", "lift_choice",
           "lift_first_complete", "missing_objects"]
