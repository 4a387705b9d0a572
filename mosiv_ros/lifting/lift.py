"""Stage 2: lift one observed frame into simulation particles, per object, without overlap.

What it is for: ``lift`` turns an ``/mosiv/observed_objects`` cloud (occupied voxel centres per
object, see ``mosiv_ros.recon.VOXEL_FIELD``) into ``LiftedParticles``, following MOSIV's
multi-object lifting with M-PhyGs boundary handling:

0. given the next observed frames, each object's hull is first cut to the voxels that they,
   moved onto it, also hold (``consensus``: hull left by an occluding object goes);
1. each object's occupancy is resampled onto one world-aligned particle lattice of spacing h;
2. its density field is smoothed and refined so that thin parts are not eroded (``density``);
3. every cell within ``boundary_band`` outside an object's surface, or inside it, is claimed by
   that object; a cell claimed by several objects goes to the one with the smallest signed
   distance (the object it lies deepest in, or, outside all, the nearest surface), so supports
   never overlap;
4. signed distances d_i are recomputed from each object's final inside cells, so the contact
   interface is part of its surface, and band cells that now reach into another object are gone;
   where the voxels are finer than the lattice, an inside cell's d_i is also no larger than its
   distance to the voxels' own surface (capped at 0), so the surface lies to within a voxel, not
   a cell, and the boundary offset peels it in sub-cell steps (lattice distances alone put every
   outermost inside cell at -h/2); nothing is kept below a declared ground plane;
5. every particle carries V_i = V_g (sigmoid(-beta (d_i + o_s)) + eps) (M-PhyGs supplement,
   Eq. 1), V_g = h^3, with a boundary offset o_s per segment (here: per object, zero until the
   identifier optimises it), its object id, segment and material family;
6. when the cloud has the surface points' colours (``mosiv_ros.recon.COLOUR_FIELD``), every
   particle takes the colour of its object's nearest surface point: the colour under it in the
   lifted frame, with which the twin is re-rendered.

What it is not for: reconstruction (``mosiv_ros.recon``) or the simulator itself
(``simulation`` converts to ``mosiv_ros.sim.Particles``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from mosiv_ros.config import LiftingConfig
from mosiv_ros.io.recording import PointCloud
from mosiv_ros.io.scene import FAMILIES, Scene
from mosiv_ros.lifting.consensus import consensus
from mosiv_ros.lifting.density import Box, occupancy_on_lattice, refine_density, signed_distance, voxel_surface_distance
from mosiv_ros.recon.reconstruct import (
    COLOUR_FIELD,
    VOXEL_FIELD,
    ObservedFrame,
    cut_objects,
    ground_plane,
    pack_rgb,
    unpack_rgb,
)

_LOG = logging.getLogger(__name__)

UNKNOWN_MATERIAL = 255
"""``material`` code of an object whose family the scene does not declare (codes: index in
``FAMILIES``); identification chooses its family (``identify.family``)."""
_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


def boundary_volume(sdf: np.ndarray, lattice_volume: float | np.ndarray, offset: float | np.ndarray,
                    beta: float, eps: float) -> np.ndarray:
    """M-PhyGs Eq. 1: V_i = V_g (sigmoid(-beta (d_i + o_s)) + eps)."""
    x = -beta * (np.asarray(sdf, dtype=np.float64) + offset)
    sigmoid = 0.5 * (1.0 + np.tanh(0.5 * x))  # overflow-free logistic
    return np.asarray(lattice_volume, dtype=np.float64) * (sigmoid + eps)


@dataclass
class LiftedParticles:
    """Simulation particles of every object of one frame (all arrays (N,), x (N, 3) metres).

    ``sdf`` is the signed distance (m, negative inside) to the object's estimated surface,
    ``segment`` the boundary-offset segment (the object id), ``material`` the family code.
    """

    x: np.ndarray
    object_id: np.ndarray
    segment: np.ndarray
    material: np.ndarray
    sdf: np.ndarray
    lattice_volume: float
    beta: float
    eps: float
    stamp_ns: int = 0
    families: dict[int, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    seconds: float = 0.0
    rgb: np.ndarray | None = None
    """(N, 3) uint8 colour of each particle (None: the observed cloud carried no colours)."""

    @property
    def object_ids(self) -> list[int]:
        """The objects present, in id order."""
        return sorted(int(i) for i in np.unique(self.object_id))

    def volumes(self, offsets: Mapping[int, float] | None = None) -> np.ndarray:
        """Per-particle volume (m^3) for boundary offsets o_s per segment (default 0)."""
        return boundary_volume(self.sdf, self.lattice_volume, self._offsets(offsets), self.beta, self.eps)

    def solid(self, offsets: Mapping[int, float] | None = None) -> np.ndarray:
        """(N,) bool: the particles inside the surface moved by the offsets, d_i + o_s <= 0."""
        return self.sdf + self._offsets(offsets) <= 0.0

    def _offsets(self, offsets: Mapping[int, float] | None) -> np.ndarray:
        """Each particle's segment's offset o_s (0 where none is given)."""
        offset = np.zeros(len(self.x))
        for segment, value in (offsets or {}).items():
            offset[self.segment == segment] = value
        return offset

    def object_volume(self, object_id: int, offsets: Mapping[int, float] | None = None) -> float:
        """Total particle volume (m^3) of one object."""
        return float(self.volumes(offsets)[self.object_id == object_id].sum())

    def summary(self) -> str:
        """One line: particles and volume per object, and the time taken."""
        parts = [f"object {i} ({self.families.get(i, 'unknown family')}): "
                 f"{int((self.object_id == i).sum())} particles, {self.object_volume(i) * 1e6:.1f} cm^3"
                 for i in self.object_ids]
        return f"{len(self.x)} particles, {'; '.join(parts) or 'no object'} in {self.seconds * 1e3:.0f} ms"

    def to_cloud(self) -> PointCloud:
        """The ``/mosiv/particles`` cloud (DESIGN.md).

        Fields volume, material, sdf, segment, and lattice_volume, boundary_beta, boundary_eps
        (one value each, repeated on every point); ``rgb`` when the particles have colours.
        """
        n = len(self.x)
        colour = {} if self.rgb is None else {COLOUR_FIELD: pack_rgb(self.rgb)}
        return PointCloud(self.x, self.object_id, {
            "volume": self.volumes().astype(np.float32),
            "material": self.material,
            "sdf": self.sdf.astype(np.float32),
            "lattice_volume": np.full(n, self.lattice_volume, np.float32),
            "segment": self.segment,
            "boundary_beta": np.full(n, self.beta),
            "boundary_eps": np.full(n, self.eps),
            **colour,
        }, stamp_ns=self.stamp_ns)

    @classmethod
    def from_cloud(cls, cloud: PointCloud) -> LiftedParticles:
        """Read a ``/mosiv/particles`` cloud back, with the boundary settings it was lifted with.

        ValueError if it lacks a field, has no particle (nothing to simulate) or several values of
        a one-value field.
        """
        missing = [n for n in ("material", "sdf", "segment", *_ONE_VALUE_FIELDS) if n not in cloud.fields]
        if missing:
            raise ValueError(f"particle cloud lacks field(s) {missing}")
        if not len(cloud.xyz):
            raise ValueError(f"particle cloud of stamp {cloud.stamp_ns} ns is empty: no particle to simulate")
        lattice_volume, beta, eps = (_one_value(cloud, name) for name in _ONE_VALUE_FIELDS)
        rgb = unpack_rgb(cloud.fields[COLOUR_FIELD]) if COLOUR_FIELD in cloud.fields else None
        return cls(cloud.xyz.astype(np.float64), cloud.object_id, cloud.fields["segment"].astype(np.uint16),
                   cloud.fields["material"].astype(np.uint8), cloud.fields["sdf"].astype(np.float64),
                   lattice_volume, beta, eps, cloud.stamp_ns, rgb=rgb)


_ONE_VALUE_FIELDS = ("lattice_volume", "boundary_beta", "boundary_eps")
"""Fields of a particle cloud that hold one value for the whole cloud, on every point."""


def _one_value(cloud: PointCloud, name: str) -> float:
    """The value of a one-value field of a particle cloud; ValueError if it has several."""
    values = np.unique(cloud.fields[name])
    if len(values) > 1:
        raise ValueError(f"particle cloud has several values of {name}: {values.tolist()}")
    return float(values[0])


def lift(cloud: PointCloud, config: LiftingConfig, scene: Scene | None = None,
         later: Sequence[PointCloud] = ()) -> LiftedParticles:
    """Particles of every object of one observed cloud (see the module docstring).

    ``later``: the next observed clouds, at most ``config.consensus_frames`` of them used to trim
    each object's hull first (``consensus``).
    """
    start = time.perf_counter()
    h = config.particle_spacing
    if h <= 0 or config.boundary_band < 0:
        raise ValueError(f"need particle_spacing > 0 and boundary_band >= 0, got {h}, "
                         f"{config.boundary_band}")
    for observed in (cloud, *later):
        if VOXEL_FIELD not in observed.fields:
            raise ValueError(f"observed cloud at stamp {observed.stamp_ns} ns has no {VOXEL_FIELD!r} "
                             "field (not a reconstruction_node cloud)")
    if config.consensus_frames > 0 and later:
        cloud = consensus(cloud, later[:config.consensus_frames], config.consensus_max_removed)
    sizes = np.asarray(cloud.fields[VOXEL_FIELD], dtype=np.float64)
    voxel = sizes > 0
    ids = sorted(int(i) for i in np.unique(cloud.object_id[voxel]))
    if not ids:
        raise ValueError(f"observed cloud at stamp {cloud.stamp_ns} ns has no occupied voxel")
    margin = config.boundary_band + 2 * h
    claims = []  # per object: (keys, sdf) of every cell it claims
    surface = []  # per object: the voxel-resolution signed distance of those cells
    for object_id in ids:
        mine = voxel & (cloud.object_id == object_id)
        centres, size = cloud.xyz[mine].astype(np.float64), float(sizes[mine].max())
        box = Box.around(centres, size / 2, margin, h)
        occupied = occupancy_on_lattice(centres, size, box)
        inside = refine_density(occupied, config.density_iterations, config.density_threshold)
        sdf = signed_distance(inside, h)
        cells = np.argwhere(sdf < config.boundary_band)
        claims.append((_keys(box.lo + cells), sdf[tuple(cells.T)]))
        if size < h:
            surface.append(voxel_surface_distance(centres, size, box, config.density_iterations,
                                                  config.density_threshold)[tuple(cells.T)])
        else:
            surface.append(np.full(len(cells), -np.inf))
    owner = _assign(claims)
    ground = ground_plane(scene)
    x, object_id, sdf, warnings = [], [], [], []
    for k, object_id_k in enumerate(ids):
        keys, d = claims[k]
        kept = keys[owner[k]]
        inside_keys = kept[d[owner[k]] < 0]
        if len(inside_keys) == 0:
            warnings.append(f"stamp {cloud.stamp_ns} ns: object {object_id_k} lies entirely inside "
                            "other objects; it gets no particles")
            continue
        cells, inside_cells = _cells(kept), _cells(inside_keys)
        box = Box.of_cells(inside_cells, margin, h)
        grid = np.zeros(box.shape, dtype=bool)
        grid[tuple((inside_cells - box.lo).T)] = True
        # inside cells: how deep, to within a voxel where the voxels are finer than the lattice
        # (at most 0, so every inside cell stays inside at offset 0 and thin parts are kept);
        # the contact interface, cells given up to another object and the band: to within a cell
        final = np.maximum(signed_distance(grid, h)[tuple((cells - box.lo).T)],
                           np.minimum(surface[k][owner[k]], 0.0))
        keep = final < config.boundary_band
        if ground is not None:  # nothing below a declared ground, band particles included
            keep &= (cells + 0.5) * h @ ground[0] >= ground[1]
        x.append((cells[keep] + 0.5) * h)
        sdf.append(final[keep])
        object_id.append(np.full(int(keep.sum()), object_id_k, np.uint16))
    lifted = _assemble(x, object_id, sdf, config, scene, cloud.stamp_ns, warnings)
    lifted.rgb = _colours(cloud, lifted)
    lifted.seconds = time.perf_counter() - start
    return lifted


def _colours(cloud: PointCloud, lifted: LiftedParticles) -> np.ndarray | None:
    """Each particle's colour: its object's nearest coloured surface point's (None: no colours)."""
    if COLOUR_FIELD not in cloud.fields:
        return None
    surface = np.asarray(cloud.fields[VOXEL_FIELD]) == 0
    rgb = np.zeros((len(lifted.x), 3), np.uint8)
    for object_id in lifted.object_ids:
        points = surface & (cloud.object_id == object_id)
        mine = lifted.object_id == object_id
        if not points.any():
            return None
        nearest = cKDTree(cloud.xyz[points]).query(lifted.x[mine])[1]
        rgb[mine] = unpack_rgb(cloud.fields[COLOUR_FIELD][points][nearest])
    return rgb


def missing_objects(cloud: PointCloud, scene: Scene | None) -> list[int]:
    """Declared object ids without an occupied voxel in an observed cloud (none: it can be lifted).

    Empty when there is no scene declaration.
    """
    if scene is None:
        return []
    voxel = np.asarray(cloud.fields.get(VOXEL_FIELD, np.zeros(len(cloud.xyz)))) > 0
    return sorted(set(scene.ids) - set(np.unique(cloud.object_id[voxel]).tolist()))


def complete(cloud: PointCloud, scene: Scene | None) -> bool:
    """Whether an observed cloud can be lifted: each declared object (or any) has a voxel."""
    return not missing_objects(cloud, scene) and bool(np.any(np.asarray(cloud.fields.get(VOXEL_FIELD, 0)) > 0))


def lift_choice(clouds: Sequence[PointCloud], scene: Scene | None, border_wait: int) -> int | None:
    """Which cloud to lift, ``clouds`` being the observed ones from the first complete one on.

    The first complete cloud that no image border cuts (``recon.cut_objects``: an object's part
    beyond the border is not reconstructed) among the first ``border_wait + 1``; the first
    cloud when none of them is; None while fewer have come and none is.
    """
    for k, cloud in enumerate(clouds[:border_wait + 1]):
        if complete(cloud, scene) and not cut_objects(cloud):
            return k
    return 0 if len(clouds) > border_wait else None


def border_note(clouds: Sequence[PointCloud], chosen: int) -> str | None:
    """The warning for lifting ``clouds[chosen]`` (``lift_choice``) of ``clouds`` from the first complete one.

    None where no image border cuts an object of that first one.
    """
    cut = cut_objects(clouds[0])
    if chosen:
        return (f"stamp {clouds[0].stamp_ns} ns: an image border cuts objects {cut}; lifting stamp "
                f"{clouds[chosen].stamp_ns} ns, which shows them whole")
    if cut:
        return (f"stamp {clouds[0].stamp_ns} ns: an image border cuts objects {cut}, and every frame waited "
                "for; lifting it without their parts beyond the border")
    return None


def lift_first_complete(frames: Iterable[ObservedFrame], config: LiftingConfig,
                        scene: Scene | None = None) -> LiftedParticles:
    """Stage 2 in-process, as ``lifting_node`` does it: lift the first complete frame.

    Complete: every declared object has an occupied voxel (without a declaration: any object).
    Of the first complete frame and the ``config.border_wait`` after it, the first that no image
    border cuts is lifted instead (``lift_choice``). The ``config.consensus_frames`` frames after
    the lifted one trim its hulls (``consensus``).
    """
    clouds = [frame.to_cloud() for frame in frames]
    first = next((k for k, cloud in enumerate(clouds) if complete(cloud, scene)), None)
    if first is None:
        raise ValueError("no observed frame shows every declared object: nothing to lift")
    for cloud in clouds[:first]:
        _LOG.warning("stamp %d ns: objects %s not observed; waiting for a complete frame",
                     cloud.stamp_ns, missing_objects(cloud, scene))
    clouds = clouds[first:]
    chosen = lift_choice(clouds, scene, config.border_wait) or 0
    note = border_note(clouds, chosen)
    if note:
        _LOG.warning(note)
    cloud = clouds[chosen]
    lifted = lift(cloud, config, scene, clouds[chosen + 1:chosen + 1 + max(config.consensus_frames, 0)])
    for message in lifted.warnings:
        _LOG.warning(message)
    _LOG.info("lifted stamp %d ns: %s", cloud.stamp_ns, lifted.summary())
    return lifted


def _keys(cells: np.ndarray) -> np.ndarray:
    """One int64 per lattice cell (N, 3), +-2^20 cells per axis."""
    c = cells.astype(np.int64) + _KEY_OFFSET
    return (c[:, 0] << (2 * _KEY_BITS)) | (c[:, 1] << _KEY_BITS) | c[:, 2]


def _cells(keys: np.ndarray) -> np.ndarray:
    mask = (1 << _KEY_BITS) - 1
    return np.stack([keys >> (2 * _KEY_BITS), (keys >> _KEY_BITS) & mask, keys & mask], 1) - _KEY_OFFSET


def _assign(claims: list[tuple[np.ndarray, np.ndarray]]) -> list[np.ndarray]:
    """Per object, which of its claimed cells it keeps: each cell goes to its smallest sdf."""
    keys = np.concatenate([k for k, _ in claims])
    sdf = np.concatenate([d for _, d in claims])
    who = np.concatenate([np.full(len(k), i) for i, (k, _) in enumerate(claims)])
    order = np.lexsort((who, sdf, keys))  # by cell, then deepest first, ties to the lower id
    first = np.ones(len(order), dtype=bool)
    first[1:] = keys[order][1:] != keys[order][:-1]
    won = np.zeros(len(keys), dtype=bool)
    won[order[first]] = True
    bounds = np.cumsum([0] + [len(k) for k, _ in claims])
    return [won[bounds[i]:bounds[i + 1]] for i in range(len(claims))]


def _assemble(x: list, object_id: list, sdf: list, config: LiftingConfig, scene: Scene | None,
              stamp_ns: int, warnings: list[str]) -> LiftedParticles:
    ids = np.concatenate(object_id) if object_id else np.zeros(0, np.uint16)
    families = {}
    material = np.full(len(ids), UNKNOWN_MATERIAL, np.uint8)
    declared = {o.id: o.family for o in scene.objects} if scene is not None else {}
    for i in sorted(int(v) for v in np.unique(ids)):
        if declared.get(i) is not None:
            families[i] = declared[i]
            material[ids == i] = FAMILIES.index(declared[i])
        elif i not in declared:
            warnings.append(f"object {i} is not declared in the scene: material family unknown "
                            f"(code {UNKNOWN_MATERIAL})")
    return LiftedParticles(
        np.concatenate(x) if x else np.zeros((0, 3)), ids, ids.copy(), material,
        np.concatenate(sdf) if sdf else np.zeros(0), config.particle_spacing**3,
        config.boundary_beta, config.boundary_eps, stamp_ns, families, warnings)
