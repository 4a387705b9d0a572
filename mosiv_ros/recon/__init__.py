"""Stage 1, per-object 4D reconstruction from calibrated cameras, instance masks and depth.

``Reconstructor`` / ``reconstruct_recording`` (``reconstruct``) give one ``ObservedFrame`` per
frame set: per object, occupied voxel centres and surface points, and the per-view silhouettes.
``carving`` holds the occlusion-aware carving rules, ``views`` the per-camera image queries,
``evaluation`` the Chamfer figures against ground truth. No ROS here.
"""

from mosiv_ros.recon.reconstruct import (
    VOXEL_FIELD,
    ObjectGeometry,
    ObservedFrame,
    Reconstructor,
    iter_reconstruct,
    reconstruct_recording,
)

__all__ = ["VOXEL_FIELD", "ObjectGeometry", "ObservedFrame", "Reconstructor", "iter_reconstruct",
           "reconstruct_recording"]
