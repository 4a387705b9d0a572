"""Free-flight evidence: frames where an object touches nothing, and the force its centroid shows.

Analytic flights: a 4 cm cube of voxel centres moved along a trajectory integrated here (RK4)
under gravity and a known force law, each frame's cloud shifted by centroid noise.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from mosiv_ros.io.scene import Scene
from mosiv_ros.loop.freeflight import MIN_FRAMES, P_VALUE, SAME_LAW, as_law, field_law, free_flight, sparse_field
from mosiv_ros.loop.library import Context, LinearDragCandidate, QuadraticDragCandidate, WindCandidate
from mosiv_ros.loop.residual import Floor
from mosiv_ros.recon.reconstruct import ObjectGeometry, ObservedFrame
from mosiv_ros.sim.effects import FIELD_FEATURES

G = np.array([0.0, 0.0, -9.81])
DT = 1.0 / 30.0
VOXEL = 0.005
CUBE = np.stack(np.meshgrid(*[np.arange(-0.0175, 0.018, VOXEL)] * 3, indexing="ij"), -1).reshape(-1, 3)


def _path(x0, v0, force, frames: int, substeps: int = 200) -> np.ndarray:
    """(frames, 3) centroids of x'' = g + force(v), RK4."""
    x, v = np.array(x0, dtype=float), np.array(v0, dtype=float)
    out = [x.copy()]
    h = DT / substeps

    def a(v):
        return G + force(v)

    for _ in range(frames - 1):
        for _ in range(substeps):
            k1x, k1v = v, a(v)
            k2x, k2v = v + 0.5 * h * k1v, a(v + 0.5 * h * k1v)
            k3x, k3v = v + 0.5 * h * k2v, a(v + 0.5 * h * k2v)
            k4x, k4v = v + h * k3v, a(v + h * k3v)
            x = x + h / 6 * (k1x + 2 * k2x + 2 * k3x + k4x)
            v = v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        out.append(x.copy())
    return np.array(out)


def _frames(paths: dict[int, np.ndarray], noise: float = 0.0003, seed: int = 0) -> list[ObservedFrame]:
    rng = np.random.default_rng(seed)
    n = len(next(iter(paths.values())))
    frames = []
    for f in range(n):
        objects = {}
        for object_id, path in paths.items():
            cloud = CUBE + path[f] + rng.normal(0.0, noise, 3)
            objects[object_id] = ObjectGeometry(object_id, cloud, np.zeros((0, 3)), VOXEL)
        frames.append(ObservedFrame(1_000_000_000 + int(round(f * DT * 1e9)), objects))
    return frames


def _context(moving: list[bool]) -> Context:
    return Context([f"o{k}" for k in range(len(moving))], moving, Scene(), DT, [], None)


def _flight(frames, ids, reach: float = 0.02, floor: Floor | None = Floor()):
    return free_flight(frames, ids, np.arange(len(frames)) * DT, floor, G, reach)


def test_a_thrown_objects_quadratic_drag_is_found_in_free_flight_with_its_coefficient_and_velocity():
    drag = 2.0
    path = _path([-0.2, 0.0, 0.3], [1.0, 0.0, 1.5], lambda v: -drag * np.linalg.norm(v) * v, 12)
    flight = _flight(_frames({1: path}), [1])
    assert [(s.start, s.stop) for s in flight.segments] == [(0, 12)]
    assert flight.significant and flight.force(flight.null) > 1.0
    ctx = _context([True])
    fits = {c.name: flight.fit(c.force_law(ctx))
            for c in (QuadraticDragCandidate(), LinearDragCandidate(), WindCandidate())}
    quadratic = fits["drag"]
    assert quadratic.values["drag.coefficient[o0]"] == pytest.approx(drag, rel=0.05)
    assert quadratic.std["drag.coefficient[o0]"] < 0.1
    assert quadratic.initial_velocity[0] == pytest.approx([1.0, 0.0, 1.5], abs=0.02)
    assert flight.explained(quadratic) > 0.95 and not flight.acts(quadratic)  # nothing left over
    aic = {name: fit.chi2 + 2 * len(fit.values) for name, fit in fits.items()}
    assert aic["linear_drag"] - aic["drag"] > 10 and aic["wind"] - aic["drag"] > 10


def test_without_an_external_force_none_is_found_and_a_drag_that_would_show_is_ruled_out():
    path = _path([-0.2, 0.0, 0.3], [1.0, 0.0, 1.5], lambda v: np.zeros(3), 12)
    flight = _flight(_frames({1: path}), [1])
    assert not flight.significant and flight.p_value(flight.null) > P_VALUE
    law = QuadraticDragCandidate().force_law(_context([True]))
    fitted = flight.fit(law).values["drag.coefficient[o0]"]
    assert fitted < 0.1  # a drag the flight does not show
    worse = flight.chi2_at(law, {"drag.coefficient[o0]": 1.0}) - flight.null.chi2
    assert worse > chi2.ppf(1.0 - P_VALUE, 1)  # a drag of 1 1/m would have shown: ruled out


def test_only_frames_clear_of_the_floor_and_of_other_objects_are_free():
    # a cube falls from rest towards the floor; a second one beside it passes 5 mm from it at frame 3
    frames = np.arange(10)
    falling = _path([0.0, 0.0, 0.17], [0.0, 0.0, 0.0], lambda v: np.zeros(3), 10)
    passing = falling + np.outer(0.04 + 0.1 * np.abs(frames - 3), [1.0, 0.0, 0.0])
    flight = _flight(_frames({1: falling, 2: passing}, noise=0.0), [1, 2], reach=0.02)
    bottom = falling[:, 2] - 0.0175 - VOXEL / 2  # the lowest voxel's lower face
    assert np.array_equal(flight.free[:, 0], (bottom > 0.02) & (frames != 3))
    assert np.array_equal(flight.free[:, 1], flight.free[:, 0])
    for s in flight.segments:
        assert s.stop - s.start >= MIN_FRAMES and flight.free[s.start:s.stop, s.object].all()
    no_floor = _flight(_frames({1: falling}, noise=0.0), [1], floor=None)
    assert no_floor.free.all() and [(s.start, s.stop) for s in no_floor.segments] == [(0, 10)]
    assert math.isfinite(no_floor.noise[0]) and not no_floor.significant  # free fall under gravity


def test_a_force_no_named_effect_exerts_is_described_by_a_sparse_field_of_its_own_terms():
    # a sideways force that turns along the flight (a_y = 20 (x + 0.02) m/s^2, zero mid-flight):
    # no uniform or drag law explains it
    x, v = np.array([-0.2, 0.0, 0.3]), np.array([1.0, 0.0, 1.5])
    positions, h = [x.copy()], DT / 200
    for _ in range(11):
        for _ in range(200):
            a = G + np.array([0.0, 20.0 * (x[0] + 0.02), 0.0])
            x, v = x + h * v + 0.5 * h * h * a, v + h * a
        positions.append(x.copy())
    path = np.array(positions)
    flight = _flight(_frames({1: path}), [1])
    assert flight.significant
    ctx = _context([True])
    for candidate in (QuadraticDragCandidate(), LinearDragCandidate(), WindCandidate()):
        assert flight.acts(flight.fit(candidate.force_law(ctx))), candidate.name  # none explains it
    terms, origin, fit = sparse_field(flight)
    assert not flight.acts(fit) and len(terms) <= 3
    assert (FIELD_FEATURES.index("x"), 1) in terms  # a_y along x
    slope = fit.values[f"force_field.w[{3 * FIELD_FEATURES.index('x') + 1}]"]
    assert slope == pytest.approx(20.0, rel=0.1)
    ballistic = _path([-0.2, 0.0, 0.3], [1.0, 0.0, 1.5], lambda v: np.zeros(3), 12)
    assert sparse_field(_flight(_frames({1: ballistic}), [1])) is None  # no force, no field


def test_a_field_whose_terms_are_a_named_law_is_that_law_at_the_fields_coefficient():
    # over a throw in the x-z plane under linear drag: velocity terms with one coefficient are
    # linear drag (but for the centroids' noise across the plane, where the field has no term:
    # 0.3 % apart); a constant sideways term is wind; anisotropic velocity terms (0.49 apart) or
    # a term along the position (0.88-1.0) are no named law, nor velocity terms drag's (0.22)
    flight = _flight(_frames({1: _path([-0.2, 0.0, 0.3], [1.0, 0.0, 1.5], lambda v: -1.5 * v, 12)}), [1])
    ctx = _context([True])
    linear, quadratic, wind = (c.force_law(ctx) for c in (LinearDragCandidate(), QuadraticDragCandidate(),
                                                          WindCandidate()))
    one, x, vx, vz = (FIELD_FEATURES.index(name) for name in ("1", "x", "vx", "vz"))

    def field(terms, coefficients):
        law = field_law(np.zeros(3), terms)
        return law, dict(zip(law.labels, coefficients, strict=True))

    values, misfit = as_law(*field([(vx, 0), (vz, 2)], [-1.5, -1.5]), linear, flight)
    assert misfit < 0.01 and values["linear_drag.coefficient[o0]"] == pytest.approx(1.5, rel=1e-3)
    assert as_law(*field([(vx, 0), (vz, 2)], [-1.5, -1.5]), quadratic, flight)[1] > SAME_LAW
    assert as_law(*field([(vx, 0), (vz, 2)], [-1.5, -0.5]), linear, flight)[1] > SAME_LAW
    values, misfit = as_law(*field([(one, 1)], [1.5]), wind, flight)
    assert misfit < 1e-9 and values == pytest.approx({"wind.a[0]": 0.0, "wind.a[1]": 1.5})
    for law in (linear, quadratic, wind):
        assert as_law(*field([(x, 1)], [20.0]), law, flight)[1] > SAME_LAW


@pytest.mark.slow  # 6 sparse regressions, half a minute
def test_a_uniform_force_is_described_by_a_constant_term_not_by_one_the_data_cannot_tell_from_it():
    # a sideways wind of 1.5 m/s^2 on a throw whose horizontal speed stays 1 m/s: over ten frames
    # with 1 mm centroid noise, vx (constant here), |v| and a constant fit alike; among terms
    # within TIE of the best the simplest is taken (measured: the constant in 6 of 6 noise
    # draws; the least chi-square alone picked it in 1, vx, |v| vx or z^2 in the others)
    path = _path([-0.2, 0.0, 0.3], [1.0, 0.0, 1.0], lambda v: np.array([0.0, 1.5, 0.0]), 10)
    constant = 0
    for seed in range(6):
        flight = _flight(_frames({1: path}, noise=0.001, seed=seed), [1])
        terms, _, fit = sparse_field(flight)
        if terms == [(FIELD_FEATURES.index("1"), 1)]:
            constant += 1
            assert fit.values["force_field.w[1]"] == pytest.approx(1.5, abs=0.3)
    assert constant >= 5


def test_frames_where_an_object_reaches_an_image_border_are_not_free():
    # a force-free throw that enters a camera's view across its left border: carving keeps only
    # what every camera sees, so the cube is cut off there and its centroid jumps by millimetres
    from mosiv_ros.identify.observations import View

    rotation = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # looks along +y
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, [0.0, -0.6, 0.35]
    view = View("cam", np.array([[100.0, 0.0, 31.5], [0.0, 100.0, 47.5], [0.0, 0.0, 1.0]]), pose, 64, 96)
    path = _path([-0.19, 0.0, 0.3], [0.5, 0.0, 1.5], lambda v: np.zeros(3), 12)
    frames = _frames({1: path}, noise=0.0)
    for frame in frames:  # what carving keeps: the voxels whose centres the camera sees
        geometry = frame.objects[1]
        uv, _ = view.project(geometry.occupancy)
        geometry.occupancy = geometry.occupancy[uv[:, 0] >= -0.5]
    cut = [f for f, frame in enumerate(frames) if len(frame.objects[1].occupancy) < len(CUBE)]
    assert cut == [0, 1]  # the first two frames lose part of the cube
    flight = free_flight(frames, [1], np.arange(12) * DT, None, G, 0.02, views=[view])
    assert not flight.free[:2, 0].any() and flight.free[2:, 0].all()
    assert [(s.start, s.stop) for s in flight.segments] == [(2, 12)]
    assert not flight.significant
    blind = free_flight(frames, [1], np.arange(12) * DT, None, G, 0.02)  # the same without cameras
    assert blind.significant  # the cut reads as a force
