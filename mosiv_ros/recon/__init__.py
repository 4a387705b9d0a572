"""Stage 1, per-object 4D reconstruction from calibrated cameras, instance masks and depth.

``Reconstructor`` / ``reconstruct_recording`` (``reconstruct``) give one ``ObservedFrame`` per
frame set: per object, occupied voxel centres and surface points, and the per-view silhouettes.
``carving`` holds the occlusion-aware carving rules, ``views`` the per-camera image queries,
``tracks`` the surface tracks (optical flow, lifted to 3D), ``evaluation`` the Chamfer figures
and track errors against ground truth. No ROS here.
"""

from mosiv_ros.recon.reconstruct import (
    COLOUR_FIELD,
    CUT_FIELD,
    VOXEL_FIELD,
    ObjectGeometry,
    ObservedFrame,
    Reconstructor,
    cut_objects,
    iter_reconstruct,
    reconstruct_recording,
)
from mosiv_ros.recon.tracks import SurfaceTracker, SurfaceTracks, TrackPoints

__all__ = ["COLOUR_FIELD", "CUT_FIELD", "VOXEL_FIELD", "ObjectGeometry", "ObservedFrame", "Reconstructor",
           "SurfaceTracker", "SurfaceTracks", "TrackPoints", "cut_objects", "iter_reconstruct",
           "reconstruct_recording"]
