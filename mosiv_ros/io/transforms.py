"""The tree of static transforms (``/tf_static``), queried for T_world_frame along any chain.

The bag reader (cameras and the gripper's frame) and reconstruction_node (cameras) place frames in
the world with it, so that a recording read from disk and one received live follow one rule: a
chain of static transforms, each usable in either direction, from ``world``, as tf2 resolves it.

What it is for: static poses, and stamped poses in a frame they connect to the world
(``PoseStream``: the gripper's ``/gripper/pose``, received before or after its frame's
transforms); a pose between samples of a trajectory (``pose_at``: the one rule by which the
simulator's colliders move and carving places the gripper). Not for time-varying transforms
(``/tf``).
"""

from __future__ import annotations

import numpy as np

WORLD_FRAME = "world"


class StaticTransforms:
    """Static transforms by child frame; a transform published again replaces the old one."""

    def __init__(self) -> None:
        self.edges: dict[str, tuple[str, np.ndarray]] = {}

    def add(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        self.edges[child] = (parent, np.asarray(T_parent_child, dtype=np.float64))

    @property
    def frames(self) -> list[str]:
        """Every frame named so far, sorted."""
        return sorted({WORLD_FRAME, *self.edges, *(parent for parent, _ in self.edges.values())})

    def to_world(self, frame: str) -> np.ndarray | None:
        """T_world_frame along any chain of the transforms, or None while there is none."""
        neighbours: dict[str, list[tuple[str, np.ndarray]]] = {}
        for child, (parent, T) in list(self.edges.items()):  # a snapshot: add() may run meanwhile
            neighbours.setdefault(parent, []).append((child, T))
            neighbours.setdefault(child, []).append((parent, np.linalg.inv(T)))
        known = {WORLD_FRAME: np.eye(4)}
        queue = [WORLD_FRAME]
        while queue and frame not in known:
            current = queue.pop(0)
            for neighbour, T in neighbours.get(current, []):
                if neighbour not in known:
                    known[neighbour] = known[current] @ T
                    queue.append(neighbour)
        return known.get(frame)


class PoseStream:
    """Stamped poses (a PoseStamped stream), each in its own frame, placed in the world on demand.

    A pose may arrive before the static transforms that connect its frame to the world: poses are
    kept as received and resolved when asked for (``world``).
    """

    def __init__(self, transforms: StaticTransforms) -> None:
        self.transforms = transforms
        self.received: dict[int, tuple[str, np.ndarray]] = {}

    def add(self, stamp_ns: int, frame: str, T_frame_pose: np.ndarray) -> None:
        """A pose at ``stamp_ns`` in ``frame`` (one pose per stamp: a later one replaces it)."""
        self.received[int(stamp_ns)] = (frame, np.asarray(T_frame_pose, dtype=np.float64))

    def world(self) -> tuple[list[tuple[int, np.ndarray]], list[str]]:
        """(stamp_ns, T_world_pose) in stamp order, and the frames no transforms reach yet."""
        received = sorted(list(self.received.items()))  # a snapshot: add() may run meanwhile
        placed = {frame: self.transforms.to_world(frame) for frame in {frame for _, (frame, _) in received}}
        poses = [(stamp, placed[frame] @ T) for stamp, (frame, T) in received if placed[frame] is not None]
        return poses, sorted(frame for frame, T in placed.items() if T is None)


def pose_at(times: np.ndarray, positions: np.ndarray, quaternions: np.ndarray,
            t: float) -> tuple[np.ndarray, np.ndarray]:
    """Position (3,) and unit quaternion (x, y, z, w) at ``t`` on a sampled trajectory.

    ``times`` (T,) strictly increasing, ``positions`` (T, 3), ``quaternions`` (T, 4) unit. Between
    two samples the position is interpolated linearly and the rotation by slerp (the short way);
    at or before the first sample and at or after the last the pose is that sample's, exactly.
    """
    i, s = segment(times, t)
    j = min(i + 1, len(times) - 1)
    if s == 0.0:
        return np.array(positions[i], dtype=np.float64), np.array(quaternions[i], dtype=np.float64)
    return (1 - s) * positions[i] + s * positions[j], slerp(quaternions[i], quaternions[j], s)


def segment(times: np.ndarray, t: float) -> tuple[int, float]:
    """(i, s): ``t`` lies s of the way from sample i to i + 1 (s = 0 at and beyond the ends)."""
    if t <= times[0] or len(times) == 1:
        return 0, 0.0
    if t >= times[-1]:
        return len(times) - 1, 0.0
    i = int(np.searchsorted(times, t, side="right") - 1)
    return i, float((t - times[i]) / (times[i + 1] - times[i]))


def slerp(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    """The unit quaternion s of the way from a to b along the shorter arc."""
    dot = float(np.dot(a, b))
    if dot < 0.0:
        b, dot = -np.asarray(b), -dot
    dot = min(dot, 1.0)
    if dot > 0.9995:
        q = a + s * (b - a)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1 - s) * theta) * a + np.sin(s * theta) * b) / np.sin(theta)
