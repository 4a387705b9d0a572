"""From stage 1-2 outputs and a scene declaration to a ``FitProblem`` for the identifier.

Turns the observed frames (``recon.ObservedFrame``: per-object occupancy per frame, filtered
masks), the particles lifted from the first frame (``lifting.LiftedParticles``), the camera
calibration and the scene declaration into what ``identify.fit`` needs:

- observations: per object its occupied voxel centres per frame (volumes, like the simulated
  particles), the frames' masks and cameras for the silhouette loss; frames must be evenly
  spaced (their spacing is the simulation's frame time) but for frames the stream lost: such a
  gap is simulated through with nothing observed (no loss term), with a warning, as long as
  ``MIN_OBSERVED_FRACTION`` of the frames remain;
- surface tracks (``ObservedFrame.tracks``), with ``ProblemOptions.use_tracks``: those alive at
  the first frame, each attached to its own object's nearest particles there
  (``TrackAttachment``; a track farther than ``ATTACH_REACH`` particle spacings from them is
  dropped, with a log line saying how many), followed over the later frames;
- the simulator set-up: grid spacing twice the particle spacing, a domain around everything
  observed (and the floor), the declared ground (friction 0.5 to start with unless declared),
  gravity (declared or (0, 0, -9.81)), the declared effects with their declared values, and the
  gripper as a kinematic collider along its recorded poses;
- the M-PhyGs boundary of the lifted particles (their signed distances), whose per-object
  offset is fitted when lifting sampled a band outside the surface;
- each object's material family: the declared one; for an object whose family the declaration
  leaves open (declared without one, or not declared), ``ProblemOptions.families`` (the choice
  of ``identify.family``) or else ``ProblemOptions.default_family``;
- the free parameters: for each object the parameters its family uses that the declaration does
  not give, each object's friction only when there are other objects to touch, and the ground
  friction unless declared. Density stays at its declared or default value unless
  ``ProblemOptions.fit_density``, and then in a scene of several objects only its ratios are
  fitted. Motion cannot tell mass: scaling every density and every stress-like parameter
  (moduli, yield stress, viscosity) alike changes nothing, while the ratio of two objects'
  densities shows where they push on each other. So every undeclared density is free except,
  when no density is declared, the lowest-id object's: it stays at its default and sets the
  scale.

What it is for: the glue between stages. What it is not for: fitting (``identify.fit``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from mosiv_ros.identify.fit import Boundary, FitProblem
from mosiv_ros.identify.observations import ATTACH_REACH, Observations, TrackAttachment, View
from mosiv_ros.io.recording import Recording
from mosiv_ros.io.scene import Scene
from mosiv_ros.lifting.lift import LiftedParticles
from mosiv_ros.recon.reconstruct import ObservedFrame
from mosiv_ros.recon.tracks import SurfaceTracks, TrackPoints
from mosiv_ros.sim import ObjectModel, Particles, SimConfig, domain_around
from mosiv_ros.sim.materials import FAMILY_PARAMS
from mosiv_ros.simulation import colliders_of, declared_params, effects_of, ground_of, to_sim_particles

_LOG = logging.getLogger(__name__)

FRAME_SPACING_TOLERANCE = 0.1
"""Largest deviation of a frame spacing from a whole number of frame times, as a fraction of one."""
MIN_OBSERVED_FRACTION = 0.5
"""Least fraction of a window's frames (first to last observed) that must have been observed."""


class ProblemError(ValueError):
    """The stage outputs cannot make a fit problem (uneven frames, unknown object, ...)."""


@dataclass
class ProblemOptions:
    """Choices the caller makes: the family of objects the declaration leaves open, the margin.

    ``families`` gives such objects' family by id; the others get ``default_family``.
    ``fit_density``: fit the undeclared densities' ratios (see the module docstring).
    ``use_tracks``: attach the frames' surface tracks for the track loss (when they have any).
    """

    default_family: str = "elastic"
    margin: float = 0.1
    use_masks: bool = True
    use_tracks: bool = True
    families: dict[int, str] = field(default_factory=dict)
    fit_density: bool = False


def object_name(scene: Scene, object_id: int) -> str:
    """The declared name of an object, or ``object_<id>`` for an undeclared one."""
    item = next((o for o in scene.objects if o.id == object_id), None)
    return item.name if item is not None else f"object_{object_id}"


def views_of(recording: Recording) -> list[View]:
    """The recording's cameras as identify views (pinhole; distortion must be absent)."""
    views = []
    for name, camera in sorted(recording.cameras.items()):
        k = camera.intrinsics
        if np.any(k.D):
            _LOG.warning("camera %s has lens distortion; the silhouette loss ignores it", name)
        views.append(View(name, k.K, camera.T_world_optical, k.width, k.height))
    return views


def frame_steps(stamps_ns: Sequence[int]) -> tuple[float, list[int]]:
    """The frame time (s) of observed stamps, and the simulation frame of each (the first: 0).

    A stream may lose frames: a spacing of n frame times (to within ``FRAME_SPACING_TOLERANCE``
    of one) puts the next stamp n frames on, past a gap of n - 1 frames. The frame time is the
    median of the spacings about as small as the smallest (those without a gap). ProblemError
    if a spacing is no such multiple, or if fewer than ``MIN_OBSERVED_FRACTION`` of the frames
    from the first stamp to the last remain.
    """
    if len(stamps_ns) < 2:
        raise ProblemError(f"need at least 2 observed frames, got {len(stamps_ns)}")
    gaps = np.diff(np.asarray(stamps_ns, dtype=np.int64)) * 1e-9
    if gaps.min() <= 0:
        raise ProblemError("observed frames are not in stamp order, or two share a stamp")
    frame_dt = float(np.median(gaps[gaps < 1.5 * gaps.min()]))
    steps = np.rint(gaps / frame_dt)
    worst = int(np.argmax(np.abs(gaps - steps * frame_dt)))
    if abs(gaps[worst] - steps[worst] * frame_dt) > FRAME_SPACING_TOLERANCE * frame_dt:
        raise ProblemError(
            f"observed frames are not evenly spaced: frames {worst} and {worst + 1} are "
            f"{gaps[worst] * 1e3:.1f} ms apart, not a whole number of frame times "
            f"({frame_dt * 1e3:.1f} ms); the fit needs one simulation frame per observed frame")
    index = np.concatenate([[0], np.cumsum(steps)]).astype(int).tolist()
    if len(stamps_ns) < MIN_OBSERVED_FRACTION * (index[-1] + 1):
        raise ProblemError(
            f"too few frames remain: {len(stamps_ns)} of the {index[-1] + 1} frames from stamp "
            f"{stamps_ns[0]} ns to {stamps_ns[-1]} ns were observed (at least "
            f"{MIN_OBSERVED_FRACTION:.0%} are needed)")
    return frame_dt, index


def build_problem(frames: Sequence[ObservedFrame], lifted: LiftedParticles, scene: Scene,
                  views: Sequence[View] = (), gripper_poses: Sequence[tuple[int, np.ndarray]] = (),
                  options: ProblemOptions | None = None) -> FitProblem:
    """The fit problem of a window of observed frames, starting at ``frames[0]``."""
    options = options or ProblemOptions()
    particles, ids = to_sim_particles(lifted)
    declared = {o.id: o for o in scene.objects}
    objects, free = [], []
    for object_id in ids:
        item = declared.get(object_id)
        family = (item.family if item is not None and item.family is not None
                  else options.families.get(object_id, options.default_family))
        if family not in FAMILY_PARAMS:
            raise ProblemError(f"object {object_name(scene, object_id)!r}: unknown material family "
                               f"{family!r} (known: {', '.join(FAMILY_PARAMS)})")
        known = declared_params(item)
        objects.append(ObjectModel(object_name(scene, object_id), family, known, id=object_id))
        for param in FAMILY_PARAMS[family]:
            if param == "density" or param in known or (param == "friction" and len(ids) < 2):
                continue
            if param not in free:
                free.append(param)
    stamps = [f.stamp_ns for f in frames]
    frame_dt, steps = frame_steps(stamps)
    n_frames = steps[-1] + 1
    if n_frames > len(frames):
        lost = sorted(set(range(n_frames)) - set(steps))
        _LOG.warning("%d of the %d frames from stamp %d ns on are missing (the stream lost frames %s): "
                     "the fit simulates through them and leaves them out of its losses",
                     len(lost), n_frames, stamps[0], ", ".join(map(str, lost)))
    # a frame the stream lost: no points and no masks, so that no loss term compares with it
    points = [[np.zeros((0, 3)) for _ in ids] for _ in range(n_frames)]
    masks = [{} for _ in range(n_frames)] if options.use_masks else []
    for frame, step in zip(frames, steps, strict=True):
        points[step] = [_points(frame, object_id) for object_id in ids]
        if options.use_masks:
            masks[step] = dict(frame.masks)
    spacing = lifted.lattice_volume ** (1 / 3)
    tracks = _attached_tracks(frames, steps, particles, ids, spacing) if options.use_tracks else None
    observations = Observations(frame_dt, points, list(ids), list(views), masks, stamps[0], tracks)
    ground = ground_of(scene)
    if ground is not None and scene.ground.friction is None:
        free.append("ground.friction")
    everything = np.concatenate([particles.x] + [p for frame in points for p in frame if len(p)])
    dx = 2.0 * spacing
    lo, hi = domain_around(everything, dx, options.margin,
                           floor=ground.height if ground is not None else None)
    config = SimConfig(dx=dx, lo=lo, hi=hi, frame_dt=frame_dt, ground=ground,
                       effects=effects_of(scene, objects),
                       colliders=colliders_of(scene, gripper_poses, stamps[0]))
    fixed = {o.name: set(o.params) for o in objects}  # declared values stay as declared
    if options.fit_density and len(objects) > 1:
        open_density = [o for o in objects if "density" not in o.params]
        if len(open_density) == len(objects):  # nothing declared sets the scale: the first does
            fixed[open_density.pop(0).name].add("density")
        if open_density:
            free.append("density")
    band = float(max(lifted.sdf.max(), 0.0))  # the boundary band lifting sampled outside
    boundary = Boundary(lifted.sdf, lifted.lattice_volume, lifted.beta, lifted.eps, band)
    problem = FitProblem(objects, particles, observations, config, free, fixed, boundary)
    _LOG.info("fit problem: %d objects (%s), %d particles, %d frames at %.1f fps, dx %.3f m, "
              "free: %s", len(objects), ", ".join(f"{o.name}: {o.family}" for o in objects),
              len(particles.x), n_frames, 1 / frame_dt, dx, ", ".join(free))
    return problem


def _attached_tracks(frames: Sequence[ObservedFrame], steps: list[int], particles: Particles,
                     ids: list[int], spacing: float) -> TrackAttachment | None:
    """The frames' surface tracks attached to the particles (None: the frames have no tracks)."""
    if all(f.tracks is None or not len(f.tracks.track_id) for f in frames):
        return None
    tracks = SurfaceTracks.of([f.tracks or TrackPoints.empty(f.stamp_ns) for f in frames])
    # on the simulation's frames: a frame the stream lost has no track alive
    positions = np.full((steps[-1] + 1, len(tracks.track_id), 3), np.nan)
    confidence = np.zeros(positions.shape[:2])
    positions[steps], confidence[steps] = tracks.positions, tracks.confidence
    attachment, dropped = TrackAttachment.attach(positions, confidence, tracks.object_id, ids, particles.x,
                                                 particles.object_index, spacing)
    _LOG.info("surface tracks: %d attached to the particles, %d dropped (farther than %.1f particle "
              "spacings from their object's particles)", attachment.n_tracks, dropped, ATTACH_REACH)
    return attachment if attachment.n_tracks else None


def _points(frame: ObservedFrame, object_id: int) -> np.ndarray:
    geometry = frame.objects.get(object_id)
    if geometry is None:
        return np.zeros((0, 3))
    return np.asarray(geometry.occupancy, dtype=np.float64)
