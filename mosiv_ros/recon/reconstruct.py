"""Stage 1: per-object geometry of every frame set, from calibrated cameras, masks and depth.

What it is for: ``Reconstructor.reconstruct`` turns one ``FrameSet`` into an ``ObservedFrame``:
per object, the centres of its occupied voxels and its surface points, kept apart per object
(never a union set), plus the filtered instance masks from which each object's per-view
silhouette is read for the 2D loss. ``reconstruct_recording`` runs it over a whole
``Recording`` (the in-process pipeline); ``reconstruction_node`` runs it on live topics.
What it is not for: lifting to simulation particles (``mosiv_ros.lifting``) or evaluation
against ground truth (``evaluation``).

Per frame set: each object is carved on its own (``carving``); a voxel that two objects' carvings
both keep (they hide each other, or the masks cannot tell them apart) goes to the object more
views show there (first counting, with depth, only the views whose measured surface passes
through the voxel), ties to the object whose own evidence is nearer (its uncontested voxels and
depth returns). A declared gripper at its pose (``gripper``) hides what lies behind it where
the masks leave it as background, and its own space stays empty. Surface points are the
object's depth returns that agree with its volume when the recording has depth, otherwise the
centres of its boundary voxels. Each surface point has a colour: its pixel's, for a depth return;
for a boundary voxel, the mean colour of the pixels whose rays first enter the object's voxels in
it (the nearest such voxel's where no ray does). With a ``SurfaceTracker`` the frame also carries
the object's surface tracks (``tracks``).

Problems that degrade a frame (a camera missing from the set, an object no camera sees, an object
cut by an image border, an object left with no voxel) never raise: they are listed in
``ObservedFrame.warnings``, which the caller reports (``iter_reconstruct`` logs them, the node
sends them to its ROS log); the cameras whose border cuts an object are also in
``ObservedFrame.cut``, for the run's report.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from mosiv_ros.config import ReconstructionConfig
from mosiv_ros.io.recording import Camera, FrameSet, PointCloud, Recording, match_frames
from mosiv_ros.io.scene import Scene
from mosiv_ros.recon.carving import Lattice, carve_object
from mosiv_ros.recon.gripper import GripperShape, gripper_at
from mosiv_ros.recon.tracks import SurfaceTracker, TrackPoints
from mosiv_ros.recon.views import View, look_at_box

_LOG = logging.getLogger(__name__)

VOXEL_FIELD = "voxel_size"
"""Cloud field: edge (m) of the voxel a point is the centre of; 0 for a surface point."""
COLOUR_FIELD = "rgb"
"""Cloud field (uint32, 0x00RRGGBB, as rviz reads ``rgb``): the colour seen at a surface point."""
CUT_FIELD = "cut"
"""Cloud field (uint8): 1 on every point of an object an image border cuts in this frame set
(``ObservedFrame.cut``: its part beyond the border is not reconstructed), else 0."""


def cut_objects(cloud: PointCloud) -> list[int]:
    """The ids of the objects an image border cuts in an observed cloud (none without CUT_FIELD)."""
    if CUT_FIELD not in cloud.fields:
        return []
    return sorted(int(i) for i in np.unique(cloud.object_id[np.asarray(cloud.fields[CUT_FIELD]) > 0]))


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """(N,) uint32 0x00RRGGBB of colours (N, 3) 0..255."""
    rgb = np.asarray(rgb).reshape(-1, 3).astype(np.uint32)
    return (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 colours of packed 0x00RRGGBB values (N,)."""
    packed = np.asarray(packed).astype(np.uint32)
    return np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1).astype(np.uint8)


@dataclass
class ObjectGeometry:
    """One object at one stamp: occupied voxel centres (N, 3), surface points (M, 3), metres."""

    object_id: int
    occupancy: np.ndarray
    surface: np.ndarray
    voxel_size: float
    cameras: tuple[str, ...] = ()
    """Cameras whose (filtered) mask shows the object."""
    colour: np.ndarray | None = None
    """(M, 3) uint8 RGB seen at each surface point (None: not known, as from a cloud without it)."""

    @property
    def volume(self) -> float:
        """Occupied volume, m^3."""
        return len(self.occupancy) * self.voxel_size**3


@dataclass
class ObservedFrame:
    """Stage 1's result for one frame set."""

    stamp_ns: int
    objects: dict[int, ObjectGeometry]
    masks: dict[str, np.ndarray] = field(default_factory=dict)
    """Filtered instance masks per camera: the silhouettes for the 2D loss (``OCCLUDED`` where the
    declared gripper covers the background: ``View.silhouette_labels``)."""
    warnings: list[str] = field(default_factory=list)
    seconds: float = 0.0
    tracks: TrackPoints | None = None
    """The surface tracks at this stamp (``recon.tracks``), when a tracker ran."""
    cut: dict[int, tuple[str, ...]] = field(default_factory=dict)
    """Per object, the cameras whose image border cuts it (its part beyond is not reconstructed)."""

    def silhouette(self, object_id: int, camera: str) -> np.ndarray:
        """(H, W) bool: where ``camera`` sees ``object_id``."""
        return self.masks[camera] == object_id

    def to_cloud(self) -> PointCloud:
        """The ``/mosiv/observed_objects`` cloud of this frame.

        Per object (in id order) its voxel centres, then its surface points; the field
        ``voxel_size`` tells them apart (see VOXEL_FIELD). ``rgb`` (COLOUR_FIELD) holds each
        surface point's colour, 0 on voxel centres; it is left out when an object's colours are
        not known. ``cut`` (CUT_FIELD) marks the objects an image border cuts.
        """
        xyz, ids, sizes = [np.zeros((0, 3))], [np.zeros(0, np.uint16)], [np.zeros(0, np.float32)]
        colours = [np.zeros(0, np.uint32)]
        for object_id in sorted(self.objects):
            geometry = self.objects[object_id]
            for points, size in ((geometry.occupancy, geometry.voxel_size), (geometry.surface, 0.0)):
                xyz.append(points)
                ids.append(np.full(len(points), object_id, np.uint16))
                sizes.append(np.full(len(points), size, np.float32))
            colours += [np.zeros(len(geometry.occupancy), np.uint32),
                        pack_rgb(geometry.colour if geometry.colour is not None
                                 else np.zeros((len(geometry.surface), 3), np.uint8))]
        ids = np.concatenate(ids)
        fields = {VOXEL_FIELD: np.concatenate(sizes),
                  CUT_FIELD: np.isin(ids, np.array(sorted(self.cut), dtype=np.int64)).astype(np.uint8)}
        if all(g.colour is not None for g in self.objects.values()):
            fields[COLOUR_FIELD] = np.concatenate(colours)
        return PointCloud(np.concatenate(xyz), ids, fields, stamp_ns=self.stamp_ns)

    @classmethod
    def from_cloud(cls, cloud: PointCloud) -> ObservedFrame:
        """An ``/mosiv/observed_objects`` cloud back as a frame (without masks).

        ``cut`` holds the objects an image border cuts, without the cameras (the cloud does not
        name them).
        """
        if VOXEL_FIELD not in cloud.fields:
            raise ValueError(f"observed cloud lacks the field {VOXEL_FIELD!r}")
        sizes = np.asarray(cloud.fields[VOXEL_FIELD], dtype=np.float64)
        objects = {}
        for object_id in np.unique(cloud.object_id).tolist():
            mine = cloud.object_id == object_id
            voxel = mine & (sizes > 0)
            size = float(sizes[voxel][0]) if voxel.any() else 0.0
            surface = mine & (sizes == 0)
            colour = (unpack_rgb(cloud.fields[COLOUR_FIELD][surface]) if COLOUR_FIELD in cloud.fields
                      else None)
            objects[int(object_id)] = ObjectGeometry(int(object_id), cloud.xyz[voxel].astype(np.float64),
                                                     cloud.xyz[surface].astype(np.float64), size,
                                                     colour=colour)
        return cls(cloud.stamp_ns, objects, cut={i: () for i in cut_objects(cloud)})

    def summary(self) -> str:
        """One line: per object voxels, surface points and volume; the time taken."""
        parts = [f"{i} ({len(g.occupancy)} voxels, {len(g.surface)} surface pts, "
                 f"{g.volume * 1e6:.0f} cm^3)" for i, g in sorted(self.objects.items())]
        return f"objects {', '.join(parts) or 'none'} in {self.seconds * 1e3:.0f} ms"


class Reconstructor:
    """Stage 1 for one camera rig: calibrations, scene and settings fixed, frame sets streamed."""

    def __init__(self, cameras: Mapping[str, Camera], config: ReconstructionConfig,
                 scene: Scene | None = None, tracker: SurfaceTracker | None = None) -> None:
        """``tracker``: the surface tracker to advance with every frame set (None: no tracks).

        It keeps its tracks across Reconstructors (a node rebuilds its Reconstructor when a
        camera joins).
        """
        if not cameras:
            raise ValueError("reconstruction needs at least one calibrated camera")
        if config.min_views < 0:
            raise ValueError(f"min_views must be >= 0, got {config.min_views}")
        self.cameras = dict(cameras)
        self.config = config
        self.scene = scene if scene is not None and scene.objects else None
        self.tracker = tracker
        self.ground = ground_plane(scene)
        self.gripper = scene.gripper if scene is not None else None
        if config.workspace:
            if len(config.workspace) != 6:
                raise ValueError(f"workspace needs 6 values [xmin, ymin, zmin, xmax, ymax, zmax], "
                                 f"got {list(config.workspace)}")
            lo, hi = config.workspace[:3], config.workspace[3:]
        else:
            lo, hi = look_at_box(self.cameras.values())
        self.lattice = Lattice.covering(lo, hi, config.voxel_size)
        # Warnings about the rig and the settings, for the caller to report once.
        self.notes = self._resolution_notes((np.asarray(lo) + np.asarray(hi)) / 2)

    def _resolution_notes(self, centre: np.ndarray) -> list[str]:
        notes = []
        if len(self.cameras) < 3:
            notes.append(f"only {len(self.cameras)} camera(s) ({', '.join(sorted(self.cameras))}): "
                         "silhouettes bound each object loosely; expect larger volumes, above all "
                         "without depth")
        for name, camera in sorted(self.cameras.items()):
            distance = float(np.linalg.norm(camera.T_world_optical[:3, 3] - centre))
            footprint = distance / float(max(camera.intrinsics.K[0, 0], camera.intrinsics.K[1, 1]))
            if self.config.voxel_size < footprint / 4:
                notes.append(
                    f"voxel_size {self.config.voxel_size * 1e3:.1f} mm is far below the "
                    f"{footprint * 1e3:.1f} mm a pixel of {name} covers at the workspace centre: "
                    f"slower, not finer; consider voxel_size >= {footprint / 2 * 1e3:.0f} mm")
        return notes

    def reconstruct(self, frame_set: FrameSet, gripper_pose: np.ndarray | None = None) -> ObservedFrame:
        """Every object of one frame set (see the module docstring).

        ``gripper_pose``: T_world_gripper of the scene's declared gripper at the set's stamp
        (``recon.gripper``: it hides what lies behind it and fills its own space); ignored
        without a declared gripper.
        """
        start = time.perf_counter()
        where = f"stamp {frame_set.stamp_ns} ns"
        warnings: list[str] = []
        unknown = sorted(set(frame_set.frames) - set(self.cameras))
        if unknown:
            raise ValueError(f"{where}: cameras {unknown} have no calibration")
        missing = sorted(set(self.cameras) - set(frame_set.frames))
        if missing:
            warnings.append(f"{where}: no frame from camera(s) {', '.join(missing)}; reconstructing "
                            f"from {', '.join(sorted(frame_set.frames))}")
        views = [View(self.cameras[name], frame, mask_filter=self.config.mask_filter,
                      use_depth=self.config.use_depth)
                 for name, frame in sorted(frame_set.frames.items())]
        inside = away = None
        if self.gripper is not None and gripper_pose is not None:
            gripper = GripperShape(self.gripper, gripper_pose)
            for view in views:
                view.hide_behind(gripper.depth(view))
            inside, away = gripper.contains, gripper.away
        min_views = self.config.min_views or len(views)
        carved: dict[int, np.ndarray] = {}
        seen_by: dict[int, tuple[str, ...]] = {}
        cut_by: dict[int, tuple[str, ...]] = {}
        for object_id in self._object_ids(views, where, warnings):
            seen_by[object_id] = tuple(v.camera for v in views if object_id in v.ids)
            if not seen_by[object_id]:
                warnings.append(f"{where}: object {self._name(object_id)} is seen by no camera; "
                                "no geometry for it in this frame")
                continue
            cut = [v.camera for v in views if object_id in v.ids and v.touches_border(object_id)]
            if cut:
                cut_by[object_id] = tuple(cut)
                beyond = ("is not reconstructed" if min_views == len(views)
                          else f"is kept only where {min_views} cameras see it")
                warnings.append(f"{where}: object {self._name(object_id)} reaches the image border "
                                f"of {', '.join(cut)}; its part beyond the border {beyond}")
            carved[object_id] = carve_object(views, object_id, self.lattice, min_views=min_views,
                                             depth_tolerance=self.config.depth_tolerance,
                                             ground=self.ground, inside=inside, away=away)
        surfaces, colours = {}, {}
        for object_id in carved:
            points, rgb = zip(*(v.surface_points(object_id) for v in views), strict=True)
            surfaces[object_id], colours[object_id] = np.concatenate(points), np.concatenate(rgb)
        occupancy = _separate(self.lattice, views, carved, surfaces)
        objects = {}
        for object_id, voxels in occupancy.items():
            if len(voxels) == 0:
                warnings.append(
                    f"{where}: object {self._name(object_id)} is seen by {', '.join(seen_by[object_id])} "
                    f"but no voxel is consistent with every view and seen by {min_views} cameras; "
                    "no geometry for it in this frame")
                continue
            near = _near(self.lattice, voxels, surfaces[object_id])
            if len(surfaces[object_id]):
                surface, colour = surfaces[object_id][near], colours[object_id][near]
            else:
                surface = self.lattice.centres(_boundary(voxels))
                colour = _voxel_colours(views, object_id, self.lattice.centres(voxels),
                                        self.lattice.voxel_size, surface)
            objects[object_id] = ObjectGeometry(object_id, self.lattice.centres(voxels), surface,
                                                self.lattice.voxel_size, seen_by[object_id], colour)
        tracks = (self.tracker.update(frame_set.stamp_ns, views, objects)
                  if self.tracker is not None else None)
        return ObservedFrame(frame_set.stamp_ns, objects, {v.camera: v.silhouette_labels() for v in views},
                             warnings, time.perf_counter() - start, tracks, cut_by)

    def _object_ids(self, views: list[View], where: str, warnings: list[str]) -> list[int]:
        seen = set().union(*(v.ids for v in views))
        if self.scene is None:
            return sorted(seen)
        undeclared = sorted(seen - set(self.scene.ids))
        if undeclared:
            warnings.append(f"{where}: mask ids {undeclared} are not declared in the scene; "
                            "treated as occluders only")
        return sorted(self.scene.ids)

    def _name(self, object_id: int) -> str:
        if self.scene is not None:
            for obj in self.scene.objects:
                if obj.id == object_id:
                    return f"{object_id} ({obj.name})"
        return str(object_id)


def ground_plane(scene: Scene | None) -> tuple[np.ndarray, float] | None:
    """(unit normal, height) of the scene's declared ground, if its height is declared."""
    if scene is None or scene.ground is None or scene.ground.height is None:
        return None
    height, normal = scene.ground.plane()
    normal = np.asarray(normal, dtype=np.float64)
    norm = float(np.linalg.norm(normal))
    return normal / norm, height / norm


def _separate(lattice: Lattice, views: list[View], carved: Mapping[int, np.ndarray],
              surfaces: Mapping[int, np.ndarray]) -> dict[int, np.ndarray]:
    """Give every voxel kept by several objects to one of them.

    The winner is the claimant that the most views with depth show at the voxel's pixel where
    their measured surface passes through the voxel (it lies at most a voxel behind it): a view
    that sees another object in front of the voxel says nothing of it there, so an object half
    buried under another keeps what the views from the side show of it. A pixel counts there
    only where its filtered label is the recorded one: at an outline the majority filter can
    give a pixel its neighbour's label while its depth is its own object's surface, and such
    pixels gave a flying ball's outline voxels to the slab behind it (the loop's free flight then
    saw them touch). Then, for the voxels
    no view's surface decides (inside the objects, or no depth), the claimant the most views
    show at the voxel's pixel; among those tied, the one whose own evidence (uncontested voxels,
    depth returns) is nearest.
    """
    keys = {i: lattice.linear(v) for i, v in carved.items()}
    all_keys, counts = np.unique(np.concatenate(list(keys.values()) or [np.zeros(0, np.int64)]),
                                 return_counts=True)
    contested = all_keys[counts > 1]
    if len(contested) == 0:
        return dict(carved)
    ids = sorted(carved)
    centres = lattice.centres(np.stack(np.unravel_index(contested, lattice.shape), axis=1))
    labels, surface_labels = [], []
    for view in views:
        u, v, z = view.project(centres)
        row, col, inside = view.pixels(u, v)
        labels.append(np.where(inside, view.labels[row, col], 0))
        if view.depth is not None:
            with np.errstate(invalid="ignore"):
                on_surface = inside & (z <= view.depth[row, col] + lattice.voxel_size)
            # only where the filtered label is the recorded one: at an outline the majority filter
            # can give a pixel its neighbour's label while its depth is its own object's surface
            agree = view.mask[row, col] == view.labels[row, col]
            surface_labels.append(np.where(on_surface & agree, view.labels[row, col], 0))
    votes = np.full((len(ids), len(contested)), -1)
    distance = np.full((len(ids), len(contested)), np.inf)
    for row, object_id in enumerate(ids):
        claims = np.isin(contested, keys[object_id])
        if not claims.any():
            continue
        votes[row, claims] = ((len(views) + 1) * sum((label[claims] == object_id).astype(int)
                                                     for label in surface_labels)
                              + sum((label[claims] == object_id).astype(int) for label in labels))
        own = carved[object_id][~np.isin(keys[object_id], contested)]
        evidence = np.concatenate([lattice.centres(own), surfaces[object_id]])
        distance[row, claims] = (cKDTree(evidence).query(centres[claims])[0] if len(evidence)
                                 else np.finfo(np.float64).max)  # no evidence of its own
    distance[votes < votes.max(axis=0)] = np.inf
    winner = np.asarray(ids)[np.argmin(distance, axis=0)]
    return {i: carved[i][~np.isin(keys[i], contested[winner != i])] for i in ids}


def _near(lattice: Lattice, voxels: np.ndarray, depth_points: np.ndarray) -> np.ndarray:
    """(M,) bool: the depth returns within one voxel of the volume."""
    lo = voxels.min(axis=0) - 1
    grid = np.zeros(voxels.max(axis=0) - lo + 2, dtype=bool)
    grid[tuple((voxels - lo).T)] = True
    index = np.floor((depth_points - lattice.origin) / lattice.voxel_size).astype(np.int64) - lo
    near = np.zeros(len(index), dtype=bool)
    ok = np.all((index >= 1) & (index < np.array(grid.shape) - 1), axis=1)
    for offset in np.ndindex(3, 3, 3):
        shifted = index[ok] + np.array(offset) - 1
        near[ok] |= grid[tuple(shifted.T)]
    return near


def _boundary(voxels: np.ndarray) -> np.ndarray:
    """The voxels (N, 3) with a face neighbour outside the set."""
    lo = voxels.min(axis=0) - 1
    grid = np.zeros(voxels.max(axis=0) - lo + 2, dtype=bool)
    grid[tuple((voxels - lo).T)] = True
    return np.argwhere(grid & ~_all_neighbours(grid)) + lo


def _voxel_colours(views: list[View], object_id: int, centres: np.ndarray, voxel_size: float,
                   surface: np.ndarray) -> np.ndarray:
    """Colours (M, 3) uint8 of surface voxel centres, from the pixels whose rays enter them first.

    Each object pixel's ray (of a pixel the recorded and the filtered mask both give the object)
    is followed to the first voxel it enters; a surface voxel takes the mean colour of those
    pixels, or the nearest such voxel's colour where no ray enters it.
    """
    hits, rgb = [], []
    for view in views:
        row, col = np.nonzero((view.labels == object_id) & (view.mask == object_id))
        points = view.first_hits(col, row, centres, voxel_size)
        found = np.isfinite(points[:, 0])
        hits.append(points[found])
        rgb.append(view.rgb[row[found], col[found]].astype(np.float64))
    hits, rgb = np.concatenate(hits), np.concatenate(rgb)
    if len(hits) == 0:
        return np.zeros((len(surface), 3), np.uint8)
    who = cKDTree(surface).query(hits)[1]
    sums = np.zeros((len(surface), 3))
    counts = np.bincount(who, minlength=len(surface))
    np.add.at(sums, who, rgb)
    seen = counts > 0
    colour = np.zeros((len(surface), 3))
    colour[seen] = sums[seen] / counts[seen, None]
    if not seen.all():
        nearest = cKDTree(surface[seen]).query(surface[~seen])[1]
        colour[~seen] = colour[seen][nearest]
    return np.round(colour).astype(np.uint8)


def _all_neighbours(grid: np.ndarray) -> np.ndarray:
    """Cells whose six face neighbours are all set (the grid has a clear one-cell border)."""
    out = np.zeros_like(grid)
    out[1:-1, 1:-1, 1:-1] = (grid[:-2, 1:-1, 1:-1] & grid[2:, 1:-1, 1:-1] & grid[1:-1, :-2, 1:-1]
                             & grid[1:-1, 2:, 1:-1] & grid[1:-1, 1:-1, :-2] & grid[1:-1, 1:-1, 2:])
    return out


def reconstruct_recording(recording: Recording, config: ReconstructionConfig,
                          scene: Scene | None = None) -> list[ObservedFrame]:
    """Stage 1 over a whole recording: one ``ObservedFrame`` per frame set, in stamp order.

    Each frame carries its surface tracks (``ObservedFrame.tracks``); ``SurfaceTracks.of``
    gathers them.

    Frame sets are matched with ``config.sync_tolerance``; a set lacking some cameras is
    reconstructed from the others (with a warning). ``scene`` defaults to the recording's.
    """
    return list(iter_reconstruct(recording, config, scene))


def iter_reconstruct(recording: Recording, config: ReconstructionConfig,
                     scene: Scene | None = None) -> Iterable[ObservedFrame]:
    """``reconstruct_recording`` one frame at a time (for progress reporting)."""
    reconstructor = Reconstructor(recording.cameras, config,
                                  scene if scene is not None else recording.scene, SurfaceTracker(config.tracks))
    for message in reconstructor.notes:
        _LOG.warning(message)
    frame_sets = match_frames(recording.cameras, int(round(config.sync_tolerance * 1e9)))
    for index, frame_set in enumerate(frame_sets):
        observed = reconstructor.reconstruct(frame_set, gripper_at(recording.gripper_poses, frame_set.stamp_ns))
        for message in observed.warnings:
            _LOG.warning(message)
        _LOG.info("frame %d/%d: %s", index + 1, len(frame_sets), observed.summary())
        yield observed
