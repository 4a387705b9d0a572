"""Solid shapes of the synthetic recorder as simulation particles, and inside tests for them.

What it is for: filling each scene object's shape (box, sphere, cylinder, torus, or a watertight
mesh loaded with trimesh) with particles on a regular lattice in the object's own frame, placing
them in the world with their initial velocities (linear + angular), colouring them, and telling
which points lie inside a shape (for overlap checks); the same for a gripper's collider shape.
What it is not for: lifting observed geometry into particles (``mosiv_ros.lifting``) or the
scene file's schema (``scene_file``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from mosiv_ros.io.errors import SceneError
from mosiv_ros.sim import sampling
from mosiv_ros.synth.scene_file import MAX_PARTICLES, GripperSpec, ObjectSpec

TEXTURE_SHADE = 0.6  # brightness of the checker texture's dark squares
_PAIRS_PER_BATCH = 250_000  # (point, triangle) pairs of a winding-number batch


def winding_number(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Generalised winding number (M,) of ``points`` (M, 3) w.r.t. ``triangles`` (F, 3, 3).

    About 1 inside a closed, outward-oriented surface and 0 outside (Jacobson et al. 2013, the
    solid angle of each triangle by Van Oosterom & Strackee 1983).
    """
    result = np.zeros(len(points))
    step = max(1, _PAIRS_PER_BATCH // max(1, len(triangles)))
    for start in range(0, len(points), step):
        p = points[start:start + step, None, None, :]
        a, b, c = (triangles[None, :, i, :] - p[:, :, 0, :] for i in range(3))
        la, lb, lc = (np.linalg.norm(e, axis=-1) for e in (a, b, c))
        det = _dot(a, np.cross(b, c))
        denominator = la * lb * lc + _dot(a, b) * lc + _dot(b, c) * la + _dot(c, a) * lb
        result[start:start + step] = 2.0 * np.arctan2(det, denominator).sum(axis=1) / (4.0 * np.pi)
    return result


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", u, v)


def load_mesh(obj: ObjectSpec, where: str) -> np.ndarray:
    """Triangles (F, 3, 3) of a mesh object, scaled, in its own frame; it must be watertight."""
    try:
        mesh = trimesh.load(obj.size["file"], force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise SceneError(f"{where}.file", f"cannot load mesh: {exc}") from None
    if len(mesh.faces) == 0 or not mesh.is_watertight:
        raise SceneError(f"{where}.file", "mesh must be a non-empty, watertight surface")
    mesh.fix_normals()
    return np.asarray(mesh.triangles, dtype=np.float64) * obj.size["scale"]


@dataclass
class Body:
    """One object's particles at t = 0: ``rest`` (N, 3) in its own frame, one particle volume."""

    spec: ObjectSpec
    rest: np.ndarray
    volume: float
    triangles: np.ndarray | None = None
    rotation: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.rotation = Rotation.from_quat(self.spec.orientation).as_matrix()

    @classmethod
    def sample(cls, obj: ObjectSpec, spacing: float, where: str, budget: float) -> Body:
        """Fill ``obj``'s shape with a lattice of ``spacing``; SceneError if it is too small.

        Also a SceneError, before anything is allocated, when the lattice that the shape is cut
        from would hold more than ``budget`` points (what ``MAX_PARTICLES`` leaves).
        """
        s = obj.size
        triangles = load_mesh(obj, where) if obj.shape == "mesh" else None
        lo, hi = _bounds(obj, triangles)
        points = float(np.prod(sampling.lattice_counts(lo, hi, spacing)))
        if points > budget:
            raise SceneError("simulation.particle_spacing",
                             f"{where} ({obj.name!r}) would take {points:.3g} particles at a spacing of "
                             f"{spacing:g} m: with the objects before it more than {MAX_PARTICLES} "
                             "(raise simulation.particle_spacing or make the object smaller)")
        if obj.shape == "box":
            rest, volume = sampling.box(np.zeros(3), s["size"] / 2, spacing)
        elif obj.shape == "sphere":
            rest, volume = sampling.sphere(np.zeros(3), s["radius"], spacing)
        elif obj.shape == "cylinder":
            rest, volume = sampling.cylinder(np.zeros(3), s["radius"], s["height"] / 2, spacing)
        elif obj.shape == "torus":
            rest, volume = sampling.torus(np.zeros(3), s["major_radius"], s["minor_radius"], spacing)
        else:
            lattice = sampling.lattice(lo, hi, spacing)
            rest, volume = lattice[winding_number(lattice, triangles) > 0.5], spacing**3
        if len(rest) < 8:
            raise SceneError(where, f"only {len(rest)} particles fit in this {obj.shape} at a spacing of "
                             f"{spacing} m: make it larger or lower simulation.particle_spacing")
        return cls(obj, rest, volume, triangles)

    @property
    def x(self) -> np.ndarray:
        """World positions (N, 3) at t = 0."""
        return self.rest @ self.rotation.T + self.spec.position

    @property
    def v(self) -> np.ndarray:
        """Initial velocities (N, 3): linear plus angular about the shape's centre."""
        return self.spec.velocity + np.cross(self.spec.angular_velocity, self.x - self.spec.position)

    @property
    def albedo(self) -> np.ndarray:
        """Per-particle colour (N, 3) 0..255: the object's colour, checkered if textured."""
        albedo = np.tile(self.spec.color, (len(self.rest), 1))
        if self.spec.texture == "checker":
            dark = np.floor(self.rest / self.spec.texture_scale).sum(axis=1) % 2 == 1
            albedo[dark] *= TEXTURE_SHADE
        return albedo

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Which world ``points`` (M, 3) lie strictly inside the shape at t = 0."""
        p = (points - self.spec.position) @ self.rotation
        s = self.spec.size
        if self.spec.shape == "box":
            return np.all(np.abs(p) < s["size"] / 2, axis=1)
        if self.spec.shape == "sphere":
            return np.linalg.norm(p, axis=1) < s["radius"]
        if self.spec.shape == "cylinder":
            return (np.linalg.norm(p[:, :2], axis=1) < s["radius"]) & (np.abs(p[:, 2]) < s["height"] / 2)
        if self.spec.shape == "torus":
            ring = np.linalg.norm(p[:, :2], axis=1) - s["major_radius"]
            return ring**2 + p[:, 2] ** 2 < s["minor_radius"] ** 2
        return winding_number(p, self.triangles) > 0.5


def _bounds(obj: ObjectSpec, triangles: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) in the object's frame of the box its sampling lattice fills (as ``sampling``'s)."""
    s = obj.size
    if obj.shape == "mesh":
        corners = triangles.reshape(-1, 3)
        return corners.min(axis=0), corners.max(axis=0)
    if obj.shape == "box":
        extent = np.asarray(s["size"]) / 2
    elif obj.shape == "sphere":
        extent = np.full(3, s["radius"])
    elif obj.shape == "cylinder":
        extent = np.array([s["radius"], s["radius"], s["height"] / 2])
    else:  # torus
        reach = s["major_radius"] + s["minor_radius"]
        extent = np.array([reach, reach, s["minor_radius"]])
    return -extent, extent


def gripper_points(gripper: GripperSpec, spacing: float) -> np.ndarray:
    """Points (M, 3) filling the gripper's shape in its own frame, for rendering it."""
    if gripper.shape == "sphere":
        return sampling.sphere(np.zeros(3), gripper.size[0], spacing)[0]
    if gripper.shape == "box":
        return sampling.box(np.zeros(3), np.array(gripper.size), spacing)[0]
    radius, half_length = gripper.size
    parts = [sampling.cylinder(np.zeros(3), radius, half_length, spacing)[0]]
    parts += [sampling.sphere((0.0, 0.0, z), radius, spacing)[0] for z in (-half_length, half_length)]
    return np.concatenate(parts)


def gripper_contains(gripper: GripperSpec, local: np.ndarray) -> np.ndarray:
    """Which points (M, 3), in the gripper's own frame, lie strictly inside its shape."""
    if gripper.shape == "sphere":
        return np.linalg.norm(local, axis=1) < gripper.size[0]
    if gripper.shape == "box":
        return np.all(np.abs(local) < np.array(gripper.size), axis=1)
    radius, half_length = gripper.size
    axis = np.clip(local[:, 2], -half_length, half_length)
    return np.linalg.norm(local - np.outer(axis, [0.0, 0.0, 1.0]), axis=1) < radius
