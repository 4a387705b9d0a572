"""The second engine (benchmarks/fem_engine.py): its physics against analytic laws, its
rasteriser against exact ray casts, and its recordings read back by the project's readers."""

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from mosiv_ros.io.bag import read_recording
from mosiv_ros.io.errors import SceneError
from mosiv_ros.loop.truth import expected
from mosiv_ros.synth.cameras import look_at, pinhole, pixel_rays
from mosiv_ros.synth.ground_truth import read_ground_truth, read_ground_truth_particles

ROOT = Path(__file__).resolve().parents[1]
_SPEC = importlib.util.spec_from_file_location("fem_engine", ROOT / "benchmarks" / "fem_engine.py")
fem_engine = importlib.util.module_from_spec(_SPEC)
sys.modules["fem_engine"] = fem_engine
_SPEC.loader.exec_module(fem_engine)

G = 9.81


def ball(centre, velocity, radius=0.02, cell=0.01, E=6.0e4, nu=0.35, density=500.0):
    mesh = fem_engine.sphere_mesh(radius, cell)
    v = np.broadcast_to(np.asarray(velocity, dtype=np.float64), mesh.nodes.shape).copy()
    return fem_engine.Body(mesh, mesh.nodes + centre, v, E, nu, density)


def centre_of_mass(fem):
    return fem.mass @ fem.x / fem.mass.sum(), fem.mass @ fem.v / fem.mass.sum()


def advance(fem, seconds):
    steps = math.ceil(seconds / fem.dt - 1e-9)
    fem.dt = seconds / steps
    for _ in range(steps):
        fem.step()


def test_free_fall_follows_the_parabola_and_keeps_the_body_undeformed():
    x0, v0 = np.array([0.0, 0.0, 1.0]), np.array([0.7, -0.2, 2.0])
    fem = fem_engine.Fem([ball(x0, v0)], floor_height=-10.0)
    rest = fem.x.copy()
    t = 0.4
    advance(fem, t)
    x, v = centre_of_mass(fem)
    g = np.array([0.0, 0.0, -G])
    # symplectic Euler lags the parabola by g t dt / 2
    np.testing.assert_allclose(x, x0 + v0 * t + g * t * t / 2, atol=G * t * fem.dt)
    np.testing.assert_allclose(v, v0 + g * t, atol=1e-9)
    assert np.abs(fem.x - rest - (x - x0)).max() < 1e-9  # uniform gravity strains nothing


@pytest.mark.parametrize("effect", ["drag", "linear_drag", "wind"])
def test_effects_move_the_body_by_their_analytic_law(effect):
    v0, t = 3.0, 0.3
    fem = fem_engine.Fem([ball([0, 0, 1], [v0, 0, 0])], gravity=(0, 0, 0), floor_height=-10.0,
                         wind=(0.0, 1.5, 0.0) if effect == "wind" else (0, 0, 0),
                         drag=[1.5] if effect == "drag" else None,
                         linear_drag=[1.5] if effect == "linear_drag" else None)
    advance(fem, t)
    v = centre_of_mass(fem)[1]
    expected_v = {"drag": [v0 / (1 + 1.5 * v0 * t), 0, 0],  # dv/dt = -c v^2
                  "linear_drag": [v0 * math.exp(-1.5 * t), 0, 0],
                  "wind": [v0, 1.5 * t, 0]}[effect]
    np.testing.assert_allclose(v, expected_v, rtol=2e-3, atol=1e-9)


def test_undamped_body_conserves_momentum_and_energy_and_damping_only_the_deformation():
    lost = {}
    for damping in (0.0, 2000.0):
        body = ball([0, 0, 0], [0.5, 0.0, 1.0])
        r = body.rest_world
        wobble = r @ np.array([[5.0, 1.0, 0.0], [1.0, -3.0, 0.5], [0.0, 0.5, 2.0]])  # a straining flow, 1/s
        body.velocity += np.cross([0.0, 8.0, 3.0], r) + wobble  # spin, and deform it
        fem = fem_engine.Fem([body], floor_height=-10.0, settings=fem_engine.FemSettings(damping=damping))
        mass = fem.mass.sum()
        wobble_energy = 0.5 * fem.mass @ ((wobble - fem.mass @ wobble / mass) ** 2).sum(axis=1)

        def state(fem=fem, mass=mass):
            # symplectic Euler's velocities lie between its positions: the mean of the velocities
            # before and after the positions x is the velocity at x (else energy drifts by O(dt))
            x, v, elastic = fem.x.copy(), fem.v.copy(), fem.elastic_energy()
            fem.step()
            v = (v + fem.v) / 2
            centre, velocity = fem.mass @ x / mass, fem.mass @ v / mass
            spin = (fem.mass[:, None] * np.cross(x - centre, v - velocity)).sum(axis=0)
            energy = 0.5 * fem.mass @ (v ** 2).sum(axis=1) + mass * G * centre[2] + elastic
            return mass * velocity, spin, energy

        t = 0.25
        fem.dt = t / math.ceil(t / fem.dt)
        p0, l0, e0 = state()
        advance(fem, t)
        p1, l1, e1 = state()
        np.testing.assert_allclose(p1, p0 + mass * np.array([0, 0, -G]) * (t + fem.dt), atol=1e-12)
        np.testing.assert_allclose(l1, l0, atol=1e-10)
        lost[damping] = (e0 - e1) / wobble_energy
    assert abs(lost[0.0]) < 0.01
    assert lost[2000.0] > 0.5


def test_box_resting_on_the_floor_settles_at_its_height_under_its_weight():
    # a 4 cm box: uniaxial sag of the centre of mass rho g H^2 / (3 E), 0.26 mm at 2 % strain at
    # the bottom (softer, the material's nonlinearity would show; linear tets are a little stiff)
    H, E, density = 0.04, 2.0e4, 1000.0
    mesh = fem_engine.box_mesh(np.array([H, H, H]), 0.005)
    body = fem_engine.Body(mesh, mesh.nodes + [0, 0, H / 2], np.zeros_like(mesh.nodes), E, 0.3, density)
    fem = fem_engine.Fem([body], friction=0.0)  # frictionless: the column's sides are free
    advance(fem, 0.3)
    heights = []
    for _ in range(10):
        advance(fem, 0.01)
        heights.append(centre_of_mass(fem)[0][2])
    sag = H / 2 - np.mean(heights)
    assert sag == pytest.approx(density * G * H * H / (3 * E), rel=0.03)
    assert np.abs(centre_of_mass(fem)[1]).max() < 1e-3  # at rest


def camera(distance, width=160, height=120):
    intrinsics = pinhole(width, height, horizontal_fov=0.8)
    return intrinsics, look_at(np.array([distance, 0.0, 0.0]), np.zeros(3))


def exact_sphere_depth(intrinsics, pose, centre, radius):
    """Depth along optical z to a true sphere for every pixel ray (inf where it misses)."""
    rays = pixel_rays(intrinsics) @ pose[:3, :3].T  # world directions, optical z = 1
    o = pose[:3, 3] - centre
    a, b, c = (rays * rays).sum(1), rays @ o, o @ o - radius * radius
    disc = b * b - a * c
    with np.errstate(invalid="ignore"):
        s = (-b - np.sqrt(disc)) / a
    return np.where(disc >= 0, s, np.inf)


def read(tmp_path, text):
    path = tmp_path / "scene.yaml"
    path.write_text(text)
    return fem_engine.read_scene(path)


@pytest.mark.parametrize("centre", [[0.0, 0.0, 0.0], [0.0, 0.12, -0.08]])
def test_sphere_mask_and_depth_match_exact_ray_casts(tmp_path, centre):
    intrinsics, pose = camera(0.5)
    radius = 0.05
    spec, settings = read(tmp_path, f"""
duration: 0.1
objects: [{{name: ball, shape: sphere, radius: {radius}, position: {centre}, family: elastic,
           texture: checker, texture_scale: 0.02}}]
ground: {{height: -1.0}}
cameras: {{placement: ring, count: 1, radius: 0.5, height: 0.0, look_at: [0, 0, 0], resolution: [8, 8], fps: 30}}
fem: {{cell: 0.005}}
""")
    fem, bodies = fem_engine.scene_fem(spec, settings)
    rgb, mask, depth = fem_engine.render(intrinsics, pose, [fem_engine.body_surfaces(bodies, spec.objects, fem.x)])
    truth = exact_sphere_depth(intrinsics, pose, np.array(centre), radius).reshape(mask.shape)
    drawn, hit = mask == 1, np.isfinite(truth)
    assert set(np.unique(mask)) == {0, 1}
    assert np.array_equal(np.isfinite(depth), drawn)  # depth exactly where something is hit
    # the mesh is inscribed in the sphere: its silhouette a little smaller, never larger
    assert 0.96 < drawn.sum() / hit.sum() <= 1.0
    assert not np.any(drawn & ~hit)
    np.testing.assert_array_less(truth[drawn] - 1e-9, depth[drawn])
    facing = binary_erosion(drawn, iterations=2)  # off the silhouette, where rays graze the facets
    assert np.max(depth[facing] - truth[facing]) < 0.01 * radius
    assert np.all(rgb[~drawn] == fem_engine.BACKGROUND)
    assert len(np.unique(rgb[drawn].reshape(-1, 3), axis=0)) > 20  # shaded and checkered


def test_floor_depth_is_the_exact_plane_within_its_square():
    intrinsics = camera(0.6)[0]
    pose = look_at(np.array([0.45, 0.1, 0.35]), np.array([0.0, 0.0, 0.0]))
    normal = np.array([0.1, 0.0, 1.0]) / np.linalg.norm([0.1, 0.0, 1.0])
    floor = fem_engine.floor_surfaces(normal, 0.0, 0.3)
    rgb, mask, depth = fem_engine.render(intrinsics, pose, [floor])
    rays = pixel_rays(intrinsics) @ pose[:3, :3].T
    s = -(pose[:3, 3] @ normal) / (rays @ normal)
    spot = pose[:3, 3] + s[:, None] * rays
    e1 = np.cross([0.0, 1.0, 0.0], normal)
    e1 /= np.linalg.norm(e1)
    inside = (s > 0) & (np.abs(spot @ e1) < 0.3) & (np.abs(spot @ np.cross(normal, e1)) < 0.3)
    inside = inside.reshape(mask.shape)
    assert np.all(mask == 0)
    seen = np.isfinite(depth)
    assert (seen != inside).sum() <= 0.002 * inside.size  # only pixel centres on the square's edges
    np.testing.assert_allclose(depth[seen & inside], s.reshape(mask.shape)[seen & inside], rtol=1e-5)
    assert len(np.unique(rgb[seen].reshape(-1, 3), axis=0)) == 2  # the checker's two squares, flat lit


SCENE = """
name: tiny
duration: 0.1
objects:
  - {name: ball, shape: sphere, radius: 0.025, position: [0.0, 0.0, 0.1], velocity: [0.3, 0.0, 0.0],
     family: elastic, params: {E: 5.0e4, nu: 0.3, density: 600, friction: 0.5}, texture: checker}
  - {name: cube, shape: box, size: [0.04, 0.04, 0.04], position: [0.0, 0.15, 0.0205], family: elastic,
     declared_params: [density], params: {E: 8.0e4, nu: 0.3, density: 1000, friction: 0.5}}
ground: {height: 0.0, half_size: 0.5}
cameras: {placement: ring, count: 2, radius: 0.5, height: 0.3, look_at: [0, 0.05, 0.05],
          resolution: [48, 36], horizontal_fov: 0.9, fps: 30}
effects:
  - {type: drag, coefficient: {ball: 1.5}, declared: false}
fem: {cell: 0.012}
"""


def test_recording_is_read_back_by_the_project_with_its_truth(tmp_path):
    bag = fem_engine.record(*read(tmp_path, SCENE), tmp_path / "bag")
    recording = read_recording(bag)
    assert sorted(recording.cameras) == ["cam0", "cam1"]
    frames = recording.cameras["cam0"].frames
    assert len(frames) == 4 and frames[0].depth.dtype == np.float32
    assert set(np.unique(np.concatenate([f.mask.ravel() for f in frames]))) == {0, 1, 2}
    declared = recording.scene
    assert [o.params for o in declared.objects] == [{}, {"density": 1000.0}]
    assert declared.effects == []  # the drag is undeclared
    truth, particles = read_ground_truth(bag), read_ground_truth_particles(bag)
    assert expected(truth) == ["drag"]
    assert particles.positions.shape[:2] == (4, len(particles.object_id))
    ball_points = particles.of_object(1)
    volume = particles.volume[particles.object_id == 1]
    # the tets' centroids weighted by volume: the ball's centre, moving at 0.3 m/s (a little drag)
    centres = np.einsum("fnk,n->fk", ball_points.astype(np.float64), volume) / volume.sum()
    np.testing.assert_allclose(centres[0], [0.0, 0.0, 0.1], atol=1e-6)
    assert 0.027 < centres[-1][0] < 0.3 * 0.1


@pytest.mark.parametrize("old, new, field", [
    ("family: elastic, params: {E: 5.0e4,", "family: plastic, params: {yield_stress: 800, E: 5.0e4,", "objects[0]"),
    ("fem: {cell: 0.012}", "fem: {cells: 0.012}", "fem.cells"),
    ("fem: {cell: 0.012}", "fem: {cell: -0.012}", "fem.cell"),
    ("{type: drag, coefficient: {ball: 1.5}, declared: false}", "{type: damping, viscosity: 1.0, declared: false}",
     "effects[0].type"),
    ("ground: {height: 0.0,", "ground: {height: 0.05,", "objects[1].position"),
])
def test_scenes_it_cannot_record_are_errors_naming_the_field(tmp_path, old, new, field):
    assert old in SCENE
    with pytest.raises(SceneError) as error:
        fem_engine.scene_fem(*read(tmp_path, SCENE.replace(old, new)))
    assert error.value.field == field
