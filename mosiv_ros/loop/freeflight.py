"""Free-flight evidence: the centre-of-mass law, which no material parameter can bend.

For an object that touches nothing, M a_cm = M g + F_external whatever its material: internal
stresses cancel in the sum over the body. So in the frames where an object is in free flight,
its observed centroid shows the external force per unit mass directly, before any material fit
and whatever a material fit would make of it. ``free_flight(...)`` finds those frames and
measures that force:

- **Free frames.** An object is free at a frame when its observed occupancy clears the declared
  floor, every other object and the gripper collider by more than ``reach``: the
  reconstruction's voxel plus the reach of the model's contact (the simulation grid's spacing:
  multi-field MPM contact acts within about a cell). Runs of at least ``MIN_FRAMES`` free frames
  are the segments; a frame where the object is unseen ends a segment, and so does one where
  it reaches the border of a camera's image (within a pixel and half a voxel): the carving
  keeps only what every camera sees, so a part beyond the border is cut off and the centroid
  jumps by millimetres, which free flight would read as a force.
- **Noise.** Per object, the scatter of its centroid about a smooth curve (a polynomial of
  degree ``FLEXIBLE_DEGREE`` per segment and axis, whose residual with its degrees of freedom
  gives it), in quadrature with a systematic floor of ``SYSTEMATIC_SHARE`` of the pixel
  footprint at the object: the carving's slow drift, which the scatter does not show.
- **The test against zero.** The null model: per segment a start position and velocity, and
  the declared gravity only. Its weighted residual against the flexible curves' is a chi-square
  statistic with as many degrees of freedom as the curves have more parameters: a force acts
  when its p-value is below ``P_VALUE`` *and* the force left (the RMS acceleration of a
  quadratic or a cubic fitted to each segment's residual, whichever shows more beyond the
  noise) is at least ``MIN_FORCE`` (m/s^2; a force too small to
  matter is not worth a name even when the carving resolves it). The same test after a law's fit says whether
  a force beyond the law's remains.
- **A force law.** A candidate effect's free-flight force (``ForceLaw``: acceleration per unit
  of each knob, as a function of the state) is fitted jointly with every segment's start
  position and velocity: the trajectory is x0 + v0 t + g t^2 / 2 + sum_j theta_j D_j(t), D_j the
  double integral of the law's column j along a reference trajectory, which is refined from
  the fitted model a few times (the law's force depends on the state it changes). The knobs
  stay in their ranges (bounded least squares). The fit gives the knobs' values and standard
  deviations, the initial velocity of each object that flies from the first frame, with the
  effect in the model, and the fraction of the null model's excess residual the law explains.

- **Beyond the library.** ``sparse_field`` selects, term by term, a smooth field of few terms
  (``sim.effects.ForceField``: constant, linear and quadratic in the position, linear in the
  velocity, the speed, |v| v) that explains the force no named effect does: a description of
  the force, not of its cause.

What it is for: ranking the loop's candidates on evidence no material can absorb, their first
values and the initial velocities of their refits (``loop.closure``), and the report's plot.
What it is not for: contact phases (the loop's simulated residual covers those).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import lsq_linear
from scipy.spatial import cKDTree
from scipy.stats import chi2

from mosiv_ros.identify.observations import View
from mosiv_ros.loop.residual import Floor, observed_centroids
from mosiv_ros.recon.reconstruct import ObservedFrame
from mosiv_ros.sim.boundaries import Collider
from mosiv_ros.sim.effects import FIELD_FEATURES, field_features

MIN_FRAMES = 5
"""Fewest frames of a free-flight segment (a start position and velocity take two)."""
FLEXIBLE_DEGREE = 4
"""Degree of the smooth curve that measures the centroid's noise (lower for short segments)."""
SYSTEMATIC_SHARE = 0.1
"""A carved centroid's systematic error, as a share of what a pixel covers at the object: the
visual hull's error drifts smoothly as the object crosses pixels and its perspective changes,
which no frame-to-frame scatter shows. Measured on the loop tests' 64x48 rigs (a pixel covers
8 mm there): an effect-free throw showed 0.4 m/s^2 of such apparent force."""
P_VALUE = 1.0e-3
"""A free-flight force (or a law's share of it) is significant below this p-value."""
MIN_FORCE = 0.3
"""Least RMS external acceleration (m/s^2) over the free frames that counts as a force."""
SUBSTEPS = 16
"""Integration substeps per frame for a law's reference trajectory."""
REFINEMENTS = 4
"""Times a law's fit re-linearises about its own fitted trajectory."""
MAX_FIELD_TERMS = 6
"""Most terms of a force field that no named effect explains (``sparse_field``)."""
TIE = 2.0
"""Chi-square difference below which two field terms of one parameter each are equally good
(Akaike's criterion cannot tell them apart)."""
FIELD_BOUND = 1.0e3
"""Bound of a force field coefficient (the simulator's)."""
SAME_LAW = 0.1
"""Largest RMS difference between a named law and a field, as a share of the field's RMS
acceleration over a recording's states, at which the field is that law (``as_law``)."""

Columns = Callable[[int, np.ndarray, np.ndarray], np.ndarray]
"""columns(object index, x (n, 3), v (n, 3)) -> (n, 3, J): acceleration per unit of each knob."""


@dataclass
class ForceLaw:
    """A candidate's free-flight force: knob labels and ranges, and its acceleration columns."""

    labels: list[str]
    lower: np.ndarray
    upper: np.ndarray
    columns: Columns


@dataclass
class Segment:
    """Frames ``start`` .. ``stop - 1`` in which object ``object`` flies free."""

    object: int
    start: int
    stop: int


@dataclass
class LawFit:
    """A force law fitted to the free-flight segments."""

    values: dict[str, float]
    std: dict[str, float]
    """Standard deviations; inf for a knob that acts on no free frame (an object never free)."""
    chi2: float
    """Weighted residual (noise units squared)."""
    initial_velocity: dict[int, np.ndarray] = field(default_factory=dict)
    """Object index -> velocity (m/s) at the first frame, fitted with the law in the model (only
    for an object that flies free from the first frame on)."""
    predicted: dict[int, np.ndarray] = field(default_factory=dict)
    """Segment index -> (n, 3) fitted centroids."""


@dataclass
class FreeFlight:
    """The free-flight evidence of one recording (see the module docstring)."""

    times: np.ndarray
    observed: np.ndarray
    """(F, K, 3) observed centroids."""
    free: np.ndarray
    """(F, K) bool: the object clears everything by ``reach``."""
    segments: list[Segment]
    noise: np.ndarray
    """(K,) centroid noise (m); NaN for an object with no segment."""
    gravity: np.ndarray
    reach: float
    chi2_flexible: float = math.nan
    dof: int = 0
    """Parameters the smooth curves have beyond the null model's."""
    null: LawFit | None = None
    """The null model: gravity alone."""

    @property
    def chi2_null(self) -> float:
        return self.null.chi2 if self.null is not None else math.nan

    @property
    def frames(self) -> int:
        return sum(s.stop - s.start for s in self.segments)

    @property
    def significant(self) -> bool:
        """An external force acts in free flight (see the module docstring)."""
        return self.null is not None and self.acts(self.null)

    def p_value(self, fit: LawFit) -> float:
        """Of the fit's excess residual over the smooth curves', were it noise."""
        return float(chi2.sf(max(fit.chi2 - self.chi2_flexible, 0.0), max(self.dof - len(fit.values), 1)))

    def force(self, fit: LawFit) -> float:
        """What the fit leaves of a force (m/s^2).

        The RMS over every free frame of the acceleration of a polynomial fitted to each
        segment's residual per axis, less what the centroid noise alone puts into it; the larger
        of a quadratic's (a constant force: over a segment of five or six frames a cubic's
        acceleration is mostly noise, which hid a 1.5 m/s^2 wind) and a cubic's (a force that
        changes steadily along the flight, as one that depends on the position does).
        """
        return max(self._force(fit, degree) for degree in (2, 3))

    def _force(self, fit: LawFit, most: int) -> float:
        """``force`` from polynomials of degree at most ``most`` (fewer where a segment is short)."""
        squared, noise = [], []
        for i, s in enumerate(self.segments):
            t = self.times[s.start:s.stop] - self.times[s.start]
            degree = min(most, len(t) - 2)
            A = np.vander(t, degree + 1, increasing=True)
            coef = np.linalg.lstsq(A, self.observed[s.start:s.stop, s.object] - fit.predicted[i], rcond=None)[0]
            # d^2/dt^2 of sum_j c_j t^j, as rows acting on the coefficients
            D = np.stack([[j * (j - 1) * tk ** max(j - 2, 0) for j in range(degree + 1)] for tk in t])
            squared.append(np.sum((D @ coef) ** 2, axis=1))
            variance = np.einsum("ij,jk,ik->i", D, np.linalg.pinv(A.T @ A), D)
            noise.append(3 * self.noise[s.object] ** 2 * variance)  # three axes
        excess = np.mean(np.concatenate(squared)) - np.mean(np.concatenate(noise)) if squared else 0.0
        return float(np.sqrt(max(excess, 0.0)))

    def acts(self, fit: LawFit) -> bool:
        """A force beyond the fit's acts in free flight: significant and large enough."""
        return bool(self.segments) and self.p_value(fit) < P_VALUE and self.force(fit) >= MIN_FORCE

    def fit(self, law: ForceLaw | None) -> LawFit:
        """The law (None: the null model) fitted to every segment; see the module docstring."""
        J = 0 if law is None else len(law.labels)
        reference = [self._smooth(s) for s in self.segments]
        for _ in range(REFINEMENTS if J else 1):
            targets, columns = self._system(law, reference)
            x = _solve(columns, targets, law, len(self.segments))
            theta = x[:J]
            reference = [self._integrate(s, law, theta, x[J + 6 * i: J + 6 * i + 6])
                         for i, s in enumerate(self.segments)]
        residual = targets - columns @ x
        chi_sq = float(residual @ residual)
        std = np.sqrt(np.clip(np.diag(np.linalg.pinv(columns.T @ columns))[:J], 0.0, None))
        std[np.linalg.norm(columns[:, :J], axis=0) == 0.0] = np.inf  # a knob no free frame shows
        predicted, velocity = {}, {}
        for i, s in enumerate(self.segments):
            t = self.times[s.start:s.stop] - self.times[s.start]
            (fine, x_ref), (_, v_ref) = reference[i]
            predicted[i] = np.stack([np.interp(t, fine, x_ref[:, a]) for a in range(3)], axis=1)
            if s.start == 0:
                velocity[s.object] = v_ref[0].copy()
        labels = law.labels if J else []
        return LawFit({label: float(v) for label, v in zip(labels, theta, strict=True)},
                      {label: float(v) for label, v in zip(labels, std, strict=True)},
                      chi_sq, velocity, predicted)

    def explained(self, fit: LawFit, base: LawFit | None = None) -> float:
        """The fraction of ``base``'s excess over the smooth curves' that ``fit`` removes.

        ``base`` defaults to the null model.
        """
        base = base or self.null
        excess = base.chi2 - self.chi2_flexible
        return float((base.chi2 - fit.chi2) / excess) if excess > 0 else 0.0

    def chi2_at(self, law: ForceLaw, values: dict[str, float]) -> float:
        """The weighted residual with the knobs held at ``values`` (start states refitted)."""
        J = len(law.labels)
        theta = np.array([values.get(label, 0.0) for label in law.labels])
        reference = [self._smooth(s) for s in self.segments]
        for _ in range(REFINEMENTS):
            targets, columns = self._system(law, reference)
            rest = targets - columns[:, :J] @ theta
            nuisance = np.linalg.lstsq(columns[:, J:], rest, rcond=None)[0]
            reference = [self._integrate(s, law, theta, nuisance[6 * i: 6 * i + 6])
                         for i, s in enumerate(self.segments)]
        residual = rest - columns[:, J:] @ nuisance
        return float(residual @ residual)

    def acceleration(self, k: int, window: int = 5) -> tuple[np.ndarray, np.ndarray]:
        """(F, 3) observed free-flight acceleration of object ``k`` and its standard deviation.

        Local quadratic fits over ``window`` free frames (NaN elsewhere); for the report.
        """
        a = np.full((len(self.times), 3), np.nan)
        sd = np.full((len(self.times), 3), np.nan)
        half = window // 2
        for s in self.segments:
            if s.object != k or s.stop - s.start < window:
                continue
            for f in range(s.start + half, s.stop - half):
                t = self.times[f - half:f + half + 1] - self.times[f]
                A = np.stack([np.ones_like(t), t, 0.5 * t**2], axis=1)
                coef = np.linalg.lstsq(A, self.observed[f - half:f + half + 1, k], rcond=None)[0]
                a[f] = coef[2]
                sd[f] = self.noise[k] * math.sqrt(np.linalg.pinv(A.T @ A)[2, 2])
        return a, sd

    # --- internals -----------------------------------------------------------------------

    def _system(self, law: ForceLaw | None, reference: list) -> tuple[np.ndarray, np.ndarray]:
        """Weighted rows: targets (observed minus gravity's part) and columns [law | nuisance]."""
        J = 0 if law is None else len(law.labels)
        blocks, targets = [], []
        n_nuisance = 6 * len(self.segments)
        for i, s in enumerate(self.segments):
            t = self.times[s.start:s.stop] - self.times[s.start]
            w = 1.0 / self.noise[s.object]
            n = len(t)
            block = np.zeros((n, 3, J + n_nuisance))
            if J:
                block[:, :, :J] = self._double_integral(s, law, reference[i], t)
            for axis in range(3):
                block[:, axis, J + 6 * i + axis] = 1.0
                block[:, axis, J + 6 * i + 3 + axis] = t
            blocks.append(w * block.reshape(3 * n, -1))
            gravity_part = 0.5 * np.outer(t**2, self.gravity)
            targets.append(w * (self.observed[s.start:s.stop, s.object] - gravity_part).ravel())
        return np.concatenate(targets), np.concatenate(blocks)

    def _double_integral(self, s: Segment, law: ForceLaw, reference: tuple, t: np.ndarray) -> np.ndarray:
        """(n, 3, J): the displacement each knob's unit force adds by each frame of ``s``."""
        (tx, x), (tv, v) = reference
        a = law.columns(s.object, x, v)  # (m, 3, J) on the reference's fine grid
        dt = np.diff(tx)[:, None, None]
        velocity = np.concatenate([np.zeros((1,) + a.shape[1:]), np.cumsum(0.5 * (a[1:] + a[:-1]) * dt, axis=0)])
        position = np.concatenate([np.zeros((1,) + a.shape[1:]),
                                   np.cumsum(0.5 * (velocity[1:] + velocity[:-1]) * dt, axis=0)])
        return np.stack([np.stack([np.interp(t, tx, position[:, axis, j]) for j in range(a.shape[2])], axis=1)
                         for axis in range(3)], axis=1)

    def _smooth(self, s: Segment) -> tuple:
        """A first reference trajectory: a cubic (or lower) through the segment's centroids."""
        t = self.times[s.start:s.stop] - self.times[s.start]
        fine = np.linspace(0.0, t[-1], (len(t) - 1) * SUBSTEPS + 1)
        degree = min(3, len(t) - 1)
        coef = [np.polyfit(t, self.observed[s.start:s.stop, s.object, axis], degree) for axis in range(3)]
        x = np.stack([np.polyval(c, fine) for c in coef], axis=1)
        v = np.stack([np.polyval(np.polyder(c), fine) for c in coef], axis=1)
        return (fine, x), (fine, v)

    def _integrate(self, s: Segment, law: ForceLaw | None, theta: np.ndarray, start: np.ndarray) -> tuple:
        """The fitted model's trajectory over ``s`` (RK4 on the fine grid) from (x0, v0)."""
        t = self.times[s.start:s.stop] - self.times[s.start]
        fine = np.linspace(0.0, t[-1], (len(t) - 1) * SUBSTEPS + 1)
        x, v = start[:3].copy(), start[3:].copy()

        def accel(x: np.ndarray, v: np.ndarray) -> np.ndarray:
            a = self.gravity.copy()
            if law is not None and len(theta):
                a += law.columns(s.object, x[None], v[None])[0] @ theta
            return a

        xs, vs = [x.copy()], [v.copy()]
        for h in np.diff(fine):
            k1x, k1v = v, accel(x, v)
            k2x, k2v = v + 0.5 * h * k1v, accel(x + 0.5 * h * k1x, v + 0.5 * h * k1v)
            k3x, k3v = v + 0.5 * h * k2v, accel(x + 0.5 * h * k2x, v + 0.5 * h * k2v)
            k4x, k4v = v + h * k3v, accel(x + h * k3x, v + h * k3v)
            x = x + h / 6 * (k1x + 2 * k2x + 2 * k3x + k4x)
            v = v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
            xs.append(x.copy())
            vs.append(v.copy())
        return (fine, np.array(xs)), (fine, np.array(vs))


def combine(*laws: ForceLaw | None) -> ForceLaw | None:
    """One law whose knobs are all of ``laws``' (None where none is given)."""
    laws = [law for law in laws if law is not None]
    if len(laws) <= 1:
        return laws[0] if laws else None

    def columns(k: int, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.concatenate([law.columns(k, x, v) for law in laws], axis=-1)

    return ForceLaw([label for law in laws for label in law.labels],
                    np.concatenate([law.lower for law in laws]),
                    np.concatenate([law.upper for law in laws]), columns)


def field_law(origin: np.ndarray, terms: Sequence[tuple[int, int]]) -> ForceLaw:
    """The ``sim.effects.ForceField`` terms (feature, axis) as a law, for every object alike.

    Knob ``force_field.w[3 feature + axis]``: the acceleration along ``axis`` per unit of the
    feature, the simulator's own parameter component.
    """
    origin = np.asarray(origin, dtype=np.float64)

    def columns(k: int, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        features = field_features(x - origin, v)
        out = np.zeros(x.shape + (len(terms),))
        for j, (feature, axis) in enumerate(terms):
            out[:, axis, j] = features[:, feature]
        return out

    return ForceLaw([f"force_field.w[{3 * feature + axis}]" for feature, axis in terms],
                    np.full(len(terms), -FIELD_BOUND), np.full(len(terms), FIELD_BOUND), columns)


def sparse_field(flight: FreeFlight, base: ForceLaw | None = None,
                 max_terms: int = MAX_FIELD_TERMS) -> tuple[list[tuple[int, int]], np.ndarray, LawFit] | None:
    """A force field of few terms that explains what ``base`` leaves of the free-flight force.

    Forward selection over every (feature, axis) of ``FIELD_FEATURES``: at each step the term
    that lowers the chi-square most joins, while it lowers it beyond chance (p < ``P_VALUE``),
    until no force is left (``acts``) or ``max_terms`` have joined. Terms the data cannot tell
    apart (chi-square within ``TIE`` of the best, as a constant and |v| are over a flight at
    nearly constant speed) go to the simplest, the first in ``FIELD_FEATURES``. Position terms
    are taken about the free-flight centroids' mean. Returns (terms, origin, fit), or None where
    no such field leaves the flights force-free.
    """
    if not flight.segments:
        return None
    free = flight.observed[flight.free]
    origin = np.nanmean(free, axis=0)
    pool = [(feature, axis) for feature in range(len(FIELD_FEATURES)) for axis in range(3)]
    terms: list[tuple[int, int]] = []
    fit = flight.fit(base)
    while flight.acts(fit) and len(terms) < max_terms:
        trials = [(flight.fit(combine(base, field_law(origin, terms + [term]))), term)
                  for term in pool if term not in terms]
        least = min(trial[0].chi2 for trial in trials)
        best, term = min((t for t in trials if t[0].chi2 <= least + TIE), key=lambda trial: trial[1])
        if fit.chi2 - best.chi2 < chi2.ppf(1.0 - P_VALUE, 1):
            break
        terms.append(term)
        fit = best
    return (terms, origin, fit) if terms and not flight.acts(fit) else None


def as_law(field: ForceLaw, values: dict[str, float], law: ForceLaw,
           flight: FreeFlight) -> tuple[dict[str, float], float]:
    """``law``'s knob values nearest the force ``field`` at ``values`` exerts, and how near.

    Compared over the states ``flight``'s frames show (the loop's fitted frames): every
    object's observed centroid and its velocity (central differences) in every frame where both
    are known, contact phases too. Returns the values (bounded least squares) and the RMS
    difference of the two accelerations as a share of the field's RMS: 0 where the field is
    ``law`` (a linear drag's velocity terms with one coefficient on every axis the objects move
    along), near 1 where ``law`` cannot make it.
    """
    velocity = np.gradient(flight.observed, flight.times, axis=0)
    w = np.array([values[label] for label in field.labels])
    targets, columns = [], []
    for k in range(flight.observed.shape[1]):
        known = np.all(np.isfinite(flight.observed[:, k]) & np.isfinite(velocity[:, k]), axis=1)
        x, v = flight.observed[known, k], velocity[known, k]
        targets.append((field.columns(k, x, v) @ w).reshape(-1))
        columns.append(law.columns(k, x, v).reshape(-1, len(law.labels)))
    target, A = np.concatenate(targets), np.concatenate(columns)
    size = float(np.sqrt(np.mean(target ** 2))) if len(target) else 0.0
    if size == 0.0:
        return dict.fromkeys(law.labels, 0.0), math.inf
    theta = lsq_linear(A, target, bounds=(law.lower, law.upper)).x
    misfit = float(np.sqrt(np.mean((A @ theta - target) ** 2))) / size
    return dict(zip(law.labels, map(float, theta), strict=True)), misfit


def _at_border(view: View, points: np.ndarray, voxel: float) -> bool:
    """Whether voxels centred at ``points`` reach the border of ``view``'s image (or lie behind it).

    A voxel reaches it when its centre's projection comes within a pixel plus half the voxel's
    own footprint of the image's edge.
    """
    uv, z = view.project(points)
    if np.any(z <= 0.0):
        return True
    margin = 1.0 + 0.5 * voxel * view.K[0, 0] / z
    return bool(np.any((uv[:, 0] < margin - 0.5) | (uv[:, 0] > view.width - 0.5 - margin)
                       | (uv[:, 1] < margin - 0.5) | (uv[:, 1] > view.height - 0.5 - margin)))


def _bounding_radius(collider: Collider) -> float:
    if collider.shape == "sphere":
        return collider.size[0]
    if collider.shape == "box":
        return float(np.linalg.norm(collider.size))
    return collider.size[0] + collider.size[1]


def _solve(columns: np.ndarray, targets: np.ndarray, law: ForceLaw | None, segments: int) -> np.ndarray:
    """Least squares for [knobs | start states]: the knobs inside their ranges."""
    if law is None:
        return np.linalg.lstsq(columns, targets, rcond=None)[0]
    free = np.full(6 * segments, np.inf)
    return lsq_linear(columns, targets, bounds=(np.r_[law.lower, -free], np.r_[law.upper, free])).x


def free_flight(frames: Sequence[ObservedFrame], object_ids: Sequence[int], times: np.ndarray,
                floor: Floor | None, gravity: Sequence[float], reach: float,
                colliders: Sequence[Collider] = (), views: Sequence[View] = ()) -> FreeFlight:
    """The free-flight evidence of ``frames`` (see the module docstring).

    ``times`` (F,) s since the first frame, on the colliders' clock; ``reach`` (m) the clearance
    that counts as free. A collider counts by its bounding sphere. ``views``: the cameras, whose
    image borders end free flight and whose median pixel footprint at the objects sets the
    systematic noise floor (without them: the voxel).
    """
    observed = observed_centroids(frames, object_ids)
    F, K = observed.shape[:2]
    free = np.zeros((F, K), dtype=bool)
    voxel = np.nan
    for f, frame in enumerate(frames):
        points = []
        for object_id in object_ids:
            geometry = frame.objects.get(object_id)
            has = geometry is not None and len(geometry.occupancy) > 0
            points.append(np.asarray(geometry.occupancy, dtype=np.float64) if has else None)
            if has:
                voxel = geometry.voxel_size if math.isnan(voxel) else voxel
        trees = [cKDTree(p) if p is not None else None for p in points]
        for k, p in enumerate(points):
            if p is None:
                continue
            half = 0.5 * (frame.objects[object_ids[k]].voxel_size)
            clear = math.inf if floor is None else float(floor.above(p).min()) - half
            for j, tree in enumerate(trees):
                if j != k and tree is not None:
                    clear = min(clear, float(tree.query(p)[0].min()) - 2 * half)
            for collider in colliders:
                centre = collider.pose(float(times[f]))[0]
                clear = min(clear, float(np.linalg.norm(p - centre, axis=1).min()) - half
                            - _bounding_radius(collider))
            free[f, k] = clear > reach and not any(_at_border(view, p, 2 * half) for view in views)
    segments = []
    for k in range(K):
        f = 0
        while f < F:
            if not free[f, k]:
                f += 1
                continue
            start = f
            while f < F and free[f, k]:
                f += 1
            if f - start >= MIN_FRAMES:
                segments.append(Segment(k, start, f))
    result = FreeFlight(np.asarray(times, dtype=np.float64), observed, free, segments,
                        np.full(K, np.nan), np.asarray(gravity, dtype=np.float64), reach)
    if not segments:
        return result
    # noise: scatter about a smooth curve per segment and axis, pooled per object
    scatter, dofs, extra = [], np.zeros(K), 0
    sums = np.zeros(K)
    for s in segments:
        t = result.times[s.start:s.stop] - result.times[s.start]
        degree = min(FLEXIBLE_DEGREE, len(t) - 2)
        extra += 3 * (degree - 1)  # beyond the null's start position and velocity
        xs = observed[s.start:s.stop, s.object]
        curve = np.stack([np.polyval(np.polyfit(t, xs[:, a], degree), t) for a in range(3)], axis=1)
        scatter.append((s.object, float(np.sum((xs - curve) ** 2))))
        sums[s.object] += scatter[-1][1]
        dofs[s.object] += 3 * (len(t) - degree - 1)
    centre = np.nanmean(observed.reshape(-1, 3), axis=0)
    pixel = (float(np.median([np.linalg.norm(v.T_world_optical[:3, 3] - centre) / v.K[0, 0] for v in views]))
             if views else voxel)  # a voxel: finite, since some object was seen
    systematic = SYSTEMATIC_SHARE * pixel
    for k in range(K):
        if dofs[k] > 0:
            result.noise[k] = math.hypot(math.sqrt(sums[k] / dofs[k]), systematic)
    result.chi2_flexible = sum(rss / result.noise[k] ** 2 for k, rss in scatter)
    result.dof = extra
    result.null = result.fit(None)
    return result
