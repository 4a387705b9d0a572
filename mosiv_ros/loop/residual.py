"""Residual analysis: where, when and with what state a twin's motion departs from the data.

``analyse(frames, prediction, ...)`` compares a twin's prediction (``predict.twin.Prediction``)
with the reconstructed frames (``recon.ObservedFrame``), per object and per frame:

- centroid residual: observed minus predicted centroid (m, a vector);
- orientation residual: the angle (deg) between the principal axes of the observed and of the
  predicted points' second moments; NaN where the shape has no distinct axes (its eigenvalues
  within ``AXIS_GAP`` of each other: a cube, a ball);
- shape residual: observed minus predicted radius of gyration (m, signed: positive where the
  data are more spread than the twin) and the Chamfer distance between the two point sets with
  their centroids removed (m);
- silhouette residual: per camera, the soft-silhouette loss of the object's predicted particles
  against its observed mask (``identify.losses.silhouette_loss``; pixels of other objects are
  unknown), when silhouettes are asked for.

Time structure per object: the growth of the centroid residual (least-squares slope of its
length over time, m/s), its oscillation (sign changes of the detrended residual along its main
direction, per frame) and the jump at a contact (largest frame-to-frame change of the residual
at a frame where the object touches or leaves the floor, over the median change elsewhere).

A camera's time offset (``camera_time_offset``): the shift of the prediction's clock that best
matches that camera's silhouettes (its mask stamped t shows the scene at t + offset).

Correlation with the state: Pearson coefficients, over the frames, between the length of the
residual acceleration (second difference of the centroid residual) and the observed speed, speed
squared, height of the object's lowest point above the floor and floor contact; and per camera
the share of the silhouette residual (1 / cameras if evenly spread).

What it is for: the loop closure's evidence and its report. What it is not for: choosing an
effect (``loop.library``, ``loop.closure``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar

from mosiv_ros.identify.losses import silhouette_loss
from mosiv_ros.identify.observations import View
from mosiv_ros.io.scene import Scene
from mosiv_ros.metrics import chamfer_distance
from mosiv_ros.predict.twin import Prediction
from mosiv_ros.recon.reconstruct import ObservedFrame

AXIS_GAP = 0.15
"""Relative gap between second-moment eigenvalues below which axes are not told apart."""
SPLAT_RADIUS = 0.005
"""Soft-silhouette splat radius (m): the identifier's fallback at the default 1 cm particle
spacing, not its per-object radii calibrated on the first frame (``Identifier._splat_radius``;
0.34-0.47 spacings on the sample bags). The residual compares models on one recording, which
this radius draws alike."""


@dataclass
class Floor:
    """The declared floor plane n . x = height (n unit)."""

    height: float = 0.0
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)

    @classmethod
    def of(cls, scene: Scene) -> Floor | None:
        """The floor ``scene`` declares (None: it declares no ground)."""
        return cls(*scene.ground.plane()) if scene.ground is not None else None

    def above(self, x: np.ndarray) -> np.ndarray:
        n = np.asarray(self.normal, dtype=np.float64)
        return x @ (n / np.linalg.norm(n)) - self.height


@dataclass
class ResidualAnalysis:
    """Residuals of one twin against the observed frames (see the module docstring).

    Arrays are (F, K[, ...]) over frames and objects, NaN where an object was not observed.
    """

    times: np.ndarray
    names: list[str]
    fitted: int
    observed: np.ndarray  # (F, K, 3) observed centroids
    predicted: np.ndarray  # (F, K, 3) predicted centroids
    orientation: np.ndarray  # (F, K) deg
    shape: np.ndarray  # (F, K) radius of gyration residual, m
    shape_chamfer: np.ndarray  # (F, K) m
    silhouette: dict[str, np.ndarray]  # camera -> (F, K)
    speed: np.ndarray  # (F, K) observed, m/s
    height: np.ndarray  # (F, K) observed lowest point above the floor, m
    contact: np.ndarray  # (F, K) bool
    time_structure: list[dict] = field(default_factory=list)
    correlations: list[dict] = field(default_factory=list)

    @property
    def centroid(self) -> np.ndarray:
        """(F, K, 3) observed minus predicted centroid."""
        return self.observed - self.predicted

    def centroid_error(self, frames: slice) -> float:
        """RMS centroid distance (m) over ``frames`` and the objects seen there."""
        d = np.linalg.norm(self.centroid[frames], axis=-1)
        d = d[np.isfinite(d)]
        return float(np.sqrt(np.mean(d**2))) if len(d) else math.nan

    def errors(self) -> dict[str, float]:
        """Centroid RMS error on the fitted frames (after the first) and on the held-out ones."""
        return {"fitted": self.centroid_error(slice(1, self.fitted)),
                "held_out": self.centroid_error(slice(self.fitted, None))}

    def to_dict(self) -> dict:
        per_object = []
        for k, name in enumerate(self.names):
            per_object.append({
                "name": name,
                "centroid_residual": self.centroid[:, k].tolist(),
                "centroid_residual_norm": np.linalg.norm(self.centroid[:, k], axis=-1).tolist(),
                "orientation_deg": self.orientation[:, k].tolist(),
                "shape_rg": self.shape[:, k].tolist(),
                "shape_chamfer": self.shape_chamfer[:, k].tolist(),
                "silhouette": {c: v[:, k].tolist() for c, v in self.silhouette.items()},
                "speed": self.speed[:, k].tolist(), "height": self.height[:, k].tolist(),
                "contact": self.contact[:, k].tolist(),
                "time_structure": self.time_structure[k], "correlations": self.correlations[k],
            })
        return {"times": self.times.tolist(), "fitted_frames": self.fitted,
                "errors": self.errors(), "objects": per_object}


def observed_centroids(frames: Sequence[ObservedFrame], object_ids: Sequence[int]) -> np.ndarray:
    """(F, K, 3) centroid of each object's occupancy per frame, NaN where unseen."""
    out = np.full((len(frames), len(object_ids), 3), np.nan)
    for f, frame in enumerate(frames):
        for k, object_id in enumerate(object_ids):
            points = _points(frame, object_id)
            if len(points):
                out[f, k] = points.mean(axis=0)
    return out


def analyse(frames: Sequence[ObservedFrame], prediction: Prediction, fitted: int, floor: Floor | None,
            views: Sequence[View] = (), contact_tolerance: float = 0.01,
            device: str = "cpu") -> ResidualAnalysis:
    """The residual analysis of ``prediction`` against ``frames`` (the first ``fitted`` fitted).

    ``views`` with masks in the frames give the per-camera silhouette residual.
    """
    n = min(len(frames), len(prediction.times))
    frames = frames[:n]
    ids, index = prediction.object_ids, prediction.object_index
    K = len(ids)
    observed = observed_centroids(frames, ids)
    predicted = prediction.centroids()[:n]
    orientation = np.full((n, K), np.nan)
    shape = np.full((n, K), np.nan)
    shape_chamfer = np.full((n, K), np.nan)
    height = np.full((n, K), np.nan)
    silhouette = {v.name: np.full((n, K), np.nan) for v in views}
    for f, frame in enumerate(frames):
        for k, object_id in enumerate(ids):
            obs = _points(frame, object_id)
            pred = prediction.positions[f][index == k]
            if not len(obs):
                continue
            orientation[f, k] = _axis_angle(obs, pred)
            shape[f, k] = _gyration(obs) - _gyration(pred)
            shape_chamfer[f, k] = chamfer_distance(obs - obs.mean(axis=0), pred - pred.mean(axis=0))
            height[f, k] = floor.above(obs).min() if floor is not None else math.inf
            for view in views:
                if view.name in frame.masks:
                    loss, _ = silhouette_loss(pred, np.zeros(len(pred), dtype=int), [object_id],
                                              [view], {view.name: frame.masks[view.name]},
                                              SPLAT_RADIUS, True, device)
                    silhouette[view.name][f, k] = loss
    dt = float(prediction.times[1] - prediction.times[0]) if n > 1 else 1.0
    velocity = np.gradient(observed, dt, axis=0) if n > 1 else np.zeros_like(observed)
    speed = np.linalg.norm(velocity, axis=-1)
    contact = np.nan_to_num(height, nan=math.inf) < contact_tolerance
    analysis = ResidualAnalysis(prediction.times[:n], list(prediction.names), fitted, observed,
                                predicted, orientation, shape, shape_chamfer, silhouette, speed,
                                height, contact)
    residual = analysis.centroid
    for k in range(K):
        analysis.time_structure.append(_time_structure(analysis.times, residual[:, k], contact[:, k]))
        analysis.correlations.append(_correlations(residual[:, k], speed[:, k], height[:, k],
                                                   contact[:, k], {c: s[:, k] for c, s in silhouette.items()},
                                                   dt))
    return analysis


def camera_time_offset(prediction: Prediction, frames: Sequence[ObservedFrame], view: View,
                       span: float, tolerance: float, device: str = "cpu") -> float:
    """Time offset (s) of ``view``'s camera against ``prediction``'s clock, within +- ``span``.

    The offset that minimises the summed silhouette loss of the prediction at t + offset
    (positions interpolated linearly between its frames) against the camera's mask stamped t,
    over the frames where t +- span lies inside the prediction (bounded Brent search to
    ``tolerance``; the loss is unimodal while the shifted silhouettes overlap the observed
    ones). NaN where no frame qualifies.
    """
    times = prediction.times
    dt = float(times[1] - times[0])
    ids = list(prediction.object_ids)
    usable = []
    for frame in frames:
        t = (frame.stamp_ns - prediction.start_ns) * 1e-9
        if view.name in frame.masks and times[0] <= t - span and t + span <= times[-1]:
            usable.append((t, frame.masks[view.name]))
    if not usable:
        return math.nan

    def loss(offset: float) -> float:
        total = 0.0
        for t, mask in usable:
            at = np.clip((t + offset - times[0]) / dt, 0, len(times) - 1)
            i = min(int(at), len(times) - 2)
            x = (1 - (at - i)) * prediction.positions[i] + (at - i) * prediction.positions[i + 1]
            total += silhouette_loss(x, prediction.object_index, ids, [view], {view.name: mask},
                                     SPLAT_RADIUS, True, device)[0]
        return total

    return float(minimize_scalar(loss, bounds=(-span, span), method="bounded",
                                 options={"xatol": tolerance}).x)


def _points(frame: ObservedFrame, object_id: int) -> np.ndarray:
    geometry = frame.objects.get(object_id)
    return np.zeros((0, 3)) if geometry is None else np.asarray(geometry.occupancy, dtype=np.float64)


def _gyration(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((x - x.mean(axis=0)) ** 2, axis=1))))


def _axes(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    values, vectors = np.linalg.eigh(np.cov((x - x.mean(axis=0)).T))
    return values, vectors


def _axis_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (deg) of the rotation between the principal axes of a and b; NaN if ambiguous."""
    if len(a) < 4 or len(b) < 4:
        return math.nan
    va, ea = _axes(a)
    vb, eb = _axes(b)
    for values in (va, vb):
        gaps = np.diff(values) / max(values[-1], 1e-12)
        if np.any(gaps < AXIS_GAP):
            return math.nan
    best = math.inf
    for signs in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        fa = ea.copy()
        fa[:, 0] *= signs[0]
        fa[:, 1] *= signs[1]
        fa[:, 2] = np.cross(fa[:, 0], fa[:, 1])
        fb = eb.copy()
        fb[:, 2] = np.cross(fb[:, 0], fb[:, 1])
        rotation = fa @ fb.T
        cosine = np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0)
        best = min(best, math.degrees(math.acos(cosine)))
    return best


def _time_structure(t: np.ndarray, r: np.ndarray, contact: np.ndarray) -> dict:
    seen = np.isfinite(r[:, 0])
    if seen.sum() < 3:
        return {"growth_m_per_s": math.nan, "oscillation": math.nan, "contact_jump": math.nan}
    ts, rs = t[seen], r[seen]
    length = np.linalg.norm(rs, axis=1)
    growth = float(np.polyfit(ts, length, 1)[0])
    # main direction of the residual, its detrended signal, its sign changes per frame
    direction = np.linalg.svd(rs - rs.mean(axis=0), full_matrices=False)[2][0]
    signal = rs @ direction
    signal = signal - np.polyval(np.polyfit(ts, signal, 1), ts)
    signs = np.sign(signal[np.abs(signal) > 1e-9])
    oscillation = float(np.sum(signs[1:] != signs[:-1]) / max(len(ts) - 1, 1))
    steps = np.linalg.norm(np.diff(rs, axis=0), axis=1)
    touching = contact[seen]
    changes = touching[1:] != touching[:-1]
    jump = math.nan
    if changes.any() and (~changes).any():
        jump = float(steps[changes].max() / max(np.median(steps[~changes]), 1e-6))
    return {"growth_m_per_s": growth, "oscillation": oscillation, "contact_jump": jump}


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.std(a[ok]) == 0 or np.std(b[ok]) == 0:
        return math.nan
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def _correlations(r: np.ndarray, speed: np.ndarray, height: np.ndarray, contact: np.ndarray,
                  silhouette: dict[str, np.ndarray], dt: float) -> dict:
    accel = np.full(len(r), np.nan)
    if len(r) >= 3:
        accel[1:-1] = np.linalg.norm(r[2:] - 2 * r[1:-1] + r[:-2], axis=1) / dt**2
    totals = {c: float(np.nansum(s)) for c, s in silhouette.items()}
    whole = sum(totals.values())
    return {
        "speed": _pearson(accel, speed), "speed_squared": _pearson(accel, speed**2),
        "height": _pearson(accel, np.where(np.isfinite(height), height, np.nan)),
        "contact": _pearson(accel, contact.astype(float)),
        "camera_share": {c: (v / whole if whole > 0 else math.nan) for c, v in totals.items()},
    }
