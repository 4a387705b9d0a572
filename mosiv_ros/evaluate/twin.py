"""How well a digital twin reproduces a recording, on the fitted frames and on held-out ones.

For every frame of the recording (the twin's frames are the observation frames), per object:

- 3D: CD and EMD between the twin's particles and the reconstructed occupancy, and, for a
  synthetic recording, between the twin's particles and the ground-truth particles;
- 2D: the twin re-rendered with the synthetic recorder's renderer (each particle in the colour
  lifting gave it: the colour under it in the lifted frame) against each camera's image:
  silhouette IoU per object, PSNR and SSIM per view.

- tracks: each surface track alive at the first frame, attached to the twin's particles there
  as the fit's track loss attaches it (``TrackAttachment``), against the attached point of the
  twin's particles in every later frame it is alive: median and RMS of the 3D distance.

Frames up to the end of the fitted window are "observed", later ones "future". Parameter errors
compare estimates with ``ground_truth.yaml``: log10 ratio for scale parameters (E, yield stress,
bulk modulus, viscosity), absolute difference for nu, a vector's components and a true value of
zero, relative difference otherwise. Geometry cannot tell mass, so a fit at an assumed density
that is not the true one can only get a scale parameter right per unit density (a body's
accelerations follow div(sigma) / rho): scale parameters also carry the log10 ratio of
parameter / density against the truth's.

What it is for: the report of ``mosiv run`` and the identification benchmark.
What it is not for: losses (``identify.losses``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from mosiv_ros.identify.estimates import Estimates
from mosiv_ros.identify.observations import TrackAttachment
from mosiv_ros.io.recording import Recording, match_frames
from mosiv_ros.metrics import chamfer_distance, emd, iou, psnr, ssim
from mosiv_ros.predict.twin import Prediction
from mosiv_ros.recon.reconstruct import ObservedFrame
from mosiv_ros.recon.tracks import SurfaceTracks
from mosiv_ros.synth.render import SPLAT_RADIUS, Floor, Splats, render_view, surface_normals

LOG_SCALE = ("E", "yield_stress", "bulk_modulus", "viscosity")
SCENE = "scene"
"""The key of the scene's parameters (ground, effects) among ``parameter_errors``' objects."""
PER_DENSITY = "log10_ratio_per_density"
"""Error key of a scale parameter divided by the object's density, against the truth's."""
EMD_EVERY = 3
"""EMD (an exact assignment) on every third frame only."""


@dataclass
class FrameScores:
    """Scores of one frame: per object id CD/EMD (m), IoU; per view PSNR (dB), SSIM."""

    index: int
    t: float
    future: bool
    cd: dict[int, float] = field(default_factory=dict)
    emd: dict[int, float] = field(default_factory=dict)
    cd_truth: dict[int, float] = field(default_factory=dict)
    iou: dict[int, float] = field(default_factory=dict)
    psnr: dict[str, float] = field(default_factory=dict)
    ssim: dict[str, float] = field(default_factory=dict)


def score_frames(prediction: Prediction, frames: Sequence[ObservedFrame], recording: Recording,
                 fitted_frames: int, spacing: float, truth=None, render: bool = True
                 ) -> list[FrameScores]:
    """Scores of every observed frame that the prediction covers.

    ValueError if asked to ``render`` a prediction whose particles have no colour.
    """
    if render and prediction.rgb is None:
        raise ValueError("cannot re-render the twin: its particles have no colour (lifted from a "
                         "cloud without the 'rgb' field)")
    images = _images_by_stamp(recording)
    floor = Floor(*recording.scene.ground.plane()) if recording.scene.ground is not None else None
    scores = []
    at_stamp = {} if truth is None else {int(stamp): k for k, stamp in enumerate(truth.stamps_ns)}
    for f, frame in enumerate(frames):
        if f >= len(prediction.times):
            break
        x = prediction.positions[f]
        s = FrameScores(f, float(prediction.times[f]), f >= fitted_frames)
        for k, object_id in enumerate(prediction.object_ids):
            mine = x[prediction.object_index == k]
            geometry = frame.objects.get(object_id)
            if geometry is not None and len(geometry.occupancy):
                s.cd[object_id] = chamfer_distance(mine, geometry.occupancy)
                if f % EMD_EVERY == 0:
                    s.emd[object_id] = emd(mine, geometry.occupancy)
            if frame.stamp_ns in at_stamp:  # the truth at the frame's stamp (a fit may start later)
                s.cd_truth[object_id] = chamfer_distance(mine, truth.of_object(object_id)[at_stamp[frame.stamp_ns]])
        if render and frame.stamp_ns in images:
            _score_views(s, x, prediction, images[frame.stamp_ns], recording, spacing, floor)
        scores.append(s)
    return scores


def summarise(scores: Sequence[FrameScores]) -> dict:
    """Means over the observed and the future frames (and per object) of every score."""
    out = {}
    for part, chosen in (("observed", [s for s in scores if not s.future and s.index > 0]),
                         ("future", [s for s in scores if s.future])):
        if not chosen:
            continue
        entry = {"frames": len(chosen)}
        for key in ("cd", "emd", "cd_truth", "iou", "psnr", "ssim"):
            values = [v for s in chosen for v in getattr(s, key).values() if math.isfinite(v)]
            if values:
                entry[key] = float(np.mean(values))
            per = {}
            for s in chosen:
                for name, v in getattr(s, key).items():
                    per.setdefault(str(name), []).append(v)
            if key in ("cd", "cd_truth", "iou") and per:
                entry[f"{key}_per_object"] = {n: float(np.mean(v)) for n, v in per.items()}
        out[part] = entry
    return out


def track_errors(prediction: Prediction, tracks: SurfaceTracks, fitted_frames: int,
                 spacing: float) -> dict:
    """The twin's track error (module docstring) on the observed and the future frames.

    ``tracks`` over the prediction's frames (frame 0: the twin's first), ``spacing`` the
    particles' (m). Per part: ``median`` and ``rms`` (m) over every (frame, track) alive after
    frame 0, and their ``count``; with ``attached`` and ``dropped`` (tracks alive at frame 0 that
    no particle of their object is near).
    """
    frames = min(len(tracks.positions), len(prediction.positions))
    attached, dropped = TrackAttachment.attach(tracks.positions[:frames], tracks.confidence[:frames],
                                               tracks.object_id, prediction.object_ids,
                                               prediction.positions[0], prediction.object_index, spacing)
    out: dict = {"attached": attached.n_tracks, "dropped": dropped}
    distances = {"observed": [], "future": []}
    for f in range(1, frames):
        alive = np.isfinite(attached.positions[f, :, 0])
        error = np.linalg.norm(attached.points(prediction.positions[f])[alive]
                               - attached.positions[f, alive], axis=1)
        distances["future" if f >= fitted_frames else "observed"].append(error)
    for part, chunks in distances.items():
        values = np.concatenate(chunks) if chunks else np.zeros(0)
        if len(values):
            out[part] = {"median": float(np.median(values)), "rms": float(np.sqrt(np.mean(values**2))),
                         "count": len(values)}
    return out


def view_coverage(frames: Sequence[ObservedFrame], objects: Sequence[tuple[int, str]]) -> dict[str, dict]:
    """Per object (id, name) that the views do not show whole in every frame: which frames.

    ``cut``: the frames (indices into ``frames``) where an image border cuts the object (the
    ``cameras`` whose border does); ``missing``: the frames without geometry for it (no camera
    sees it, no voxel fits every view, or the frame set was lost). The scores of those frames
    cover only what the cameras show.
    """
    coverage = {}
    for object_id, name in objects:
        cut = [k for k, frame in enumerate(frames) if object_id in frame.cut]
        missing = [k for k, frame in enumerate(frames) if object_id not in frame.objects]
        if cut or missing:
            cameras = sorted({c for frame in frames for c in frame.cut.get(object_id, ())})
            coverage[name] = {"cut": cut, "missing": missing, "cameras": cameras}
    return coverage


def parameter_errors(estimates: Estimates, truth: dict) -> dict[str, dict[str, dict]]:
    """Per object name, per parameter: estimate, truth and the error measure of its kind.

    Every fitted value the truth holds is scored: each object's material parameters and its
    per-object effect parameters (``drag.coefficient``), and under ``SCENE`` the ground's and
    the effects' scene parameters (``ground.friction``, ``wind.a[1]``), named as the estimates
    name them.
    """
    true_objects, true_scene = truth_values(truth)
    errors: dict[str, dict[str, dict]] = {}
    for obj in estimates.objects:
        actual = true_objects.get(obj.name, {})
        for name, value in obj.params.items():
            if name not in actual:
                continue
            entry = _error(name, value, actual[name])
            if name in LOG_SCALE and "density" in obj.params and "density" in actual:
                entry[PER_DENSITY] = entry["log10_ratio"] - _log10_ratio(obj.params["density"],
                                                                         actual["density"])
            errors.setdefault(obj.name, {})[name] = entry
    scene = {name: _error(name, value, true_scene[name])
             for name, value in estimates.scene.items() if name in true_scene}
    if scene:
        errors[SCENE] = scene
    return errors


def truth_values(truth: dict) -> tuple[dict[str, dict[str, float]], dict[str, float]]:
    """A ground truth's values as the estimates name them: by object name, and of the scene."""
    objects = {o["name"]: {k: float(v) for k, v in o.get("params", {}).items()}
               for o in truth.get("objects", [])}
    scene: dict[str, float] = {}
    ground = truth.get("ground") or {}
    for key in ("height", "friction"):
        if ground.get(key) is not None:
            scene[f"ground.{key}"] = float(ground[key])
    for i, component in enumerate(ground.get("normal") or []):
        scene[f"ground.normal[{i}]"] = float(component)
    for effect in truth.get("effects", []):
        for key, value in (effect.get("params") or {}).items():
            name = f"{effect.get('type')}.{key}"
            if isinstance(value, dict):  # a value per object
                for object_name, v in value.items():
                    objects.setdefault(object_name, {})[name] = float(v)
            elif isinstance(value, list):
                scene.update({f"{name}[{i}]": float(v) for i, v in enumerate(value)})
            else:
                scene[name] = float(value)
    return objects, scene


def _error(name: str, value: float, truth: float) -> dict:
    """Estimate, truth and the error of ``name``'s kind (see the module docstring)."""
    base = name.rsplit(".", 1)[-1]
    if base in LOG_SCALE:
        kind, error = "log10_ratio", _log10_ratio(value, truth)
    elif base == "nu" or "[" in base or truth == 0:  # a vector's components; a truth of zero
        kind, error = "abs", value - truth
    else:
        kind, error = "rel", (value - truth) / truth
    return {"estimate": value, "truth": truth, kind: error}


def _log10_ratio(value: float, truth: float) -> float:
    return math.log10(value / truth) if value > 0 and truth > 0 else math.inf


def _images_by_stamp(recording: Recording) -> dict[int, dict]:
    sets = match_frames(recording.cameras)
    return {s.stamp_ns: s.frames for s in sets}


def _score_views(s: FrameScores, x: np.ndarray, prediction: Prediction, images: dict,
                 recording: Recording, spacing: float, floor) -> None:
    labels = np.asarray(prediction.object_ids)[prediction.object_index]
    normals = surface_normals(x, prediction.object_index, spacing)
    splats = Splats(x, labels.astype(np.uint16), prediction.rgb.astype(np.float64), normals,
                    SPLAT_RADIUS * spacing)
    per_object: dict[int, list[float]] = {}
    for name, image in images.items():
        camera = recording.cameras[name]
        rgb, mask, _ = render_view(camera.intrinsics, camera.T_world_optical, splats, floor)
        s.psnr[name] = psnr(rgb, image.rgb)
        s.ssim[name] = ssim(rgb, image.rgb)
        for object_id in prediction.object_ids:
            a, b = mask == object_id, image.mask == object_id
            if a.any() or b.any():
                per_object.setdefault(object_id, []).append(iou(a, b))
    s.iou = {i: float(np.mean(v)) for i, v in per_object.items()}
