"""The declared gripper in the cameras' views: what it hides from them, and the space it fills.

An instance mask that labels only the objects leaves the gripper as background (the synthetic
recorder does; so does a robot's pipeline that segments only what it manipulates). A background
pixel carves every voxel along its ray, so a gripper pressing an object would carve away the
part of the object behind it: the plate pressing ``bags/pressed_cube`` took the cube's top 2 cm
in every frame. With the gripper's declared shape (``io.scene.DeclaredGripper``) and its pose at
the frame's stamp (``/gripper/pose``), carving treats the pixels where the gripper lies in front
of a voxel as hiding it, like another object's pixels, and the space the gripper fills as empty.

What it is for: ``GripperShape`` (per view, the depth at which each pixel's ray meets the
gripper; which points lie inside it) and ``gripper_at`` (the pose at a stamp from the stamped
poses). What it is not for: the carving rules themselves (``carving``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from mosiv_ros.io.scene import DeclaredGripper
from mosiv_ros.io.transforms import pose_at, segment
from mosiv_ros.recon.views import View


def gripper_at(poses: Sequence[tuple[int, np.ndarray]], stamp_ns: int) -> np.ndarray | None:
    """T_world_gripper at ``stamp_ns`` from (stamp_ns, T) poses in stamp order (None if none).

    Interpolated as the simulator's collider moves (``io.transforms.pose_at``): linearly and by
    slerp between two poses, held still before the first and after the last.
    """
    if not poses:
        return None
    stamps = np.array([stamp for stamp, _ in poses], dtype=np.int64)
    i, s = segment(stamps, stamp_ns)
    if s == 0.0:  # at or beyond a pose: that pose, exactly
        return np.array(poses[i][1], dtype=np.float64)
    pair = np.array([poses[i][1], poses[i + 1][1]], dtype=np.float64)  # the two poses around the stamp
    position, quaternion = pose_at(stamps[i:i + 2], pair[:, :3, 3], Rotation.from_matrix(pair[:, :3, :3]).as_quat(),
                                   stamp_ns)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = Rotation.from_quat(quaternion).as_matrix(), position
    return out


class GripperShape:
    """The declared gripper at one pose T_world_gripper (its shape in its own frame, as simulated)."""

    def __init__(self, declared: DeclaredGripper, T_world_gripper: np.ndarray) -> None:
        self.shape, self.size = declared.shape, tuple(float(s) for s in declared.size)
        self.R = np.asarray(T_world_gripper, dtype=np.float64)[:3, :3]
        self.t = np.asarray(T_world_gripper, dtype=np.float64)[:3, 3]

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Whether each world point (N, 3) lies inside the gripper."""
        local = (np.asarray(points, dtype=np.float64) - self.t) @ self.R
        if self.shape == "box":
            return np.all(np.abs(local) <= self.size, axis=1)
        if self.shape == "sphere":
            return np.einsum("ij,ij->i", local, local) <= self.size[0] ** 2
        radius, half = self.size
        nearest = np.stack([np.zeros(len(local)), np.zeros(len(local)),
                            np.clip(local[:, 2], -half, half)], axis=1)
        return np.linalg.norm(local - nearest, axis=1) <= radius

    def away(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) unit vectors from the gripper's nearest point to each world point outside it.

        The direction the gripper presses what lies there (``carving``: what it hides continues
        the object that way). Zero where undefined (a point at the nearest point itself).
        """
        local = (np.asarray(points, dtype=np.float64) - self.t) @ self.R
        if self.shape == "box":
            nearest = np.clip(local, -np.asarray(self.size), np.asarray(self.size))
        elif self.shape == "sphere":
            nearest = np.zeros_like(local)
        else:
            nearest = np.zeros_like(local)
            nearest[:, 2] = np.clip(local[:, 2], -self.size[1], self.size[1])
        offset = local - nearest
        length = np.linalg.norm(offset, axis=1, keepdims=True)
        unit = np.divide(offset, length, out=np.zeros_like(offset), where=length > 0)
        return unit @ self.R.T

    def depth(self, view: View) -> np.ndarray:
        """(H, W): the optical depth at which each pixel's ray first meets the gripper, inf if never."""
        rows, cols = np.mgrid[0:view.height, 0:view.width]
        rays = view.rays(cols.ravel(), rows.ravel())  # optical z = 1: the ray parameter is the depth
        origin = (view.centre - self.t) @ self.R
        direction = rays @ self.R
        if self.shape == "box":
            hit = _box(origin, direction, np.asarray(self.size))
        elif self.shape == "sphere":
            hit = _sphere(origin, direction, np.zeros(3), self.size[0])
        else:
            hit = _capsule(origin, direction, *self.size)
        return hit.reshape(view.height, view.width)


def _box(origin: np.ndarray, direction: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Ray parameter of the first hit with the box |x| <= half (slabs), inf on a miss."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (-half - origin) / direction
        b = (half - origin) / direction
    # a ray parallel to a slab: inside it for every t, or never
    parallel = direction == 0
    inside = np.abs(origin) <= half
    a = np.where(parallel, np.where(inside, -np.inf, np.inf), a)
    b = np.where(parallel, np.where(inside, np.inf, -np.inf), b)
    near = np.minimum(a, b).max(axis=1)
    far = np.maximum(a, b).min(axis=1)
    return np.where((far >= near) & (far > 0), np.maximum(near, 0.0), np.inf)


def _sphere(origin: np.ndarray, direction: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Ray parameter of the first hit with a sphere, inf on a miss."""
    offset = origin - centre
    a = np.einsum("ij,ij->i", direction, direction)
    b = direction @ offset
    c = float(offset @ offset) - radius * radius
    disc = b * b - a * c
    with np.errstate(invalid="ignore"):
        root = np.sqrt(disc)
    near, far = (-b - root) / a, (-b + root) / a
    return np.where((disc >= 0) & (far > 0), np.maximum(near, 0.0), np.inf)


def _capsule(origin: np.ndarray, direction: np.ndarray, radius: float, half: float) -> np.ndarray:
    """Ray parameter of the first hit with a capsule along z (|z| <= half), inf on a miss."""
    hits = [_sphere(origin, direction, np.array([0.0, 0.0, z]), radius) for z in (-half, half)]
    # the side: |(o + t d)_xy| = radius with |z| <= half
    a = direction[:, 0] ** 2 + direction[:, 1] ** 2
    b = origin[0] * direction[:, 0] + origin[1] * direction[:, 1]
    c = origin[0] ** 2 + origin[1] ** 2 - radius * radius
    disc = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        root = np.sqrt(disc)
        near, far = (-b - root) / a, (-b + root) / a
    t = np.maximum(near, 0.0)
    z = origin[2] + t * direction[:, 2]
    side = np.where((disc >= 0) & (a > 0) & (far > 0) & (np.abs(z) <= half), t, np.inf)
    return np.minimum(side, np.minimum(*hits))
