"""Surface tracks on rendered scenes of known motion, the forward-backward check, and the colours
that reconstruction gives surface points and lifting gives particles."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from mosiv_ros.config import LiftingConfig, ReconstructionConfig
from mosiv_ros.io.recording import Camera, Frame, Recording
from mosiv_ros.io.scene import Scene, SceneObject
from mosiv_ros.lifting import lift_first_complete
from mosiv_ros.recon import SurfaceTracks, reconstruct_recording
from mosiv_ros.recon.evaluation import track_errors
from mosiv_ros.recon.tracks import forward_backward
from mosiv_ros.synth.cameras import look_at, pinhole
from mosiv_ros.synth.render import LIGHT_DIRECTION, Splats, render_view, surface_normals

SPACING = 0.004  # m, the rendered particles
SIDE = 0.06  # m, the cube
CHECKER = 0.015  # m, the texture's squares
FPS = 30.0
START = 1_700_000_000_000_000_000
DISTANCE = 0.5  # m, cameras from the cube
WIDTH, HEIGHT, FOV = 160, 120, 0.75
VELOCITY = np.array([0.3, 0.15, 0.0])  # m/s
SPIN = 2.0  # rad/s about the vertical through the cube's centre
FRAMES = 8


def cube(centre=(0.0, 0.0, SIDE / 2)) -> np.ndarray:
    n = round(SIDE / SPACING)
    axis = (np.arange(n) + 0.5) * SPACING - SIDE / 2
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + centre


def moved(rest: np.ndarray, t: float) -> np.ndarray:
    """The cube's particles at time t: spun about its vertical axis and translated."""
    centre = rest.mean(axis=0)
    c, s = math.cos(SPIN * t), math.sin(SPIN * t)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (rest - centre) @ R.T + centre + VELOCITY * t


def recording(paths: list[np.ndarray], albedo: np.ndarray, *, depth: bool, lit: bool = False) -> Recording:
    """Three ring cameras' views of particles on ``paths`` (one (N, 3) array per frame).

    ``lit``: every particle faces the light, so each shows exactly its albedo.
    """
    intrinsics = pinhole(WIDTH, HEIGHT, FOV)
    cameras = {}
    for index in range(3):
        angle = 2 * math.pi * index / 3 + 0.4
        eye = np.array([DISTANCE * math.cos(angle), DISTANCE * math.sin(angle), 0.3])
        T = look_at(eye, np.array([0.0, 0.0, SIDE / 2]))
        frames = []
        for k, x in enumerate(paths):
            labels = np.ones(len(x), np.uint16)
            normals = (np.tile(LIGHT_DIRECTION, (len(x), 1)) if lit
                       else surface_normals(x, labels, SPACING))
            rgb, mask, z = render_view(intrinsics, T, Splats(x, labels, albedo, normals, 0.8 * SPACING), None)
            frames.append(Frame(START + round(k * 1e9 / FPS), rgb, mask, z if depth else None))
        cameras[f"cam{index}"] = Camera(f"cam{index}", intrinsics, T, frames)
    return Recording(cameras, Scene(objects=[SceneObject(1, "cube", "elastic")]))


def checker(rest: np.ndarray) -> np.ndarray:
    dark = np.floor(rest / CHECKER).sum(axis=1) % 2 == 1
    return np.where(dark[:, None], [60.0, 80.0, 170.0], [200.0, 210.0, 240.0])


@pytest.mark.parametrize("depth", [True, False])
def test_tracks_of_a_rendered_rigid_motion_follow_the_true_motion(depth):
    rest = cube()
    paths = [moved(rest, k / FPS) for k in range(FRAMES)]
    frames = reconstruct_recording(recording(paths, checker(rest), depth=depth), ReconstructionConfig())
    tracks = SurfaceTracks.of([f.tracks for f in frames])
    errors = track_errors(tracks, np.stack(paths), np.ones(len(rest), np.uint16))
    # The cube moves 1.1 cm and turns 3.8 degrees per frame; a pixel at the cube spans
    # DISTANCE / f = 2.6 mm. A track's step can be off by up to the forward-backward tolerance
    # (1 px) and its 3D point by the depth (or visual hull) under it: bounds of one pixel's
    # footprint on the median with depth, three without (the hull lies up to a few voxels
    # outside the cube's faces), after 7 frames.
    footprint = DISTANCE / pinhole(WIDTH, HEIGHT, FOV).K[0, 0]
    last = errors[-1][np.isfinite(errors[-1])]
    assert tracks.alive[0].sum() >= 20 and len(last) >= 10, tracks.alive.sum(axis=1)
    assert np.median(last) < (1.0 if depth else 3.0) * footprint, np.nanmedian(errors, axis=1)
    # Tracks alive at frame 0 are what a loss attaches to particles: with depth, each lies on
    # the cube's rendered surface then (without, on the visual hull, which is looser).
    start = tracks.from_frame(0)
    assert np.all(np.isfinite(start.positions[0]))
    if depth:
        outside = np.abs(start.positions[0] - paths[0].mean(axis=0)).max(axis=1) - SIDE / 2
        assert np.all(np.abs(outside) < 2.0 * footprint)
    assert np.all(start.confidence[0] == 1.0) and np.all(tracks.confidence <= 1.0)


def test_the_forward_backward_check_drops_a_wrong_match_and_keeps_the_right_ones():
    rest = cube()
    paths = [moved(rest, k / FPS) for k in range(2)]
    camera = recording(paths, checker(rest), depth=True).cameras["cam0"]
    first, second = (cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY) for f in camera.frames)
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    forward, backward = flow.calc(first, second, None), flow.calc(second, first, None)
    inside = cv2.erode((camera.frames[0].mask == 1).astype(np.uint8), np.ones((5, 5), np.uint8))
    corners = cv2.goodFeaturesToTrack(first, 0, 0.01, 4, mask=inside).reshape(-1, 2).astype(np.float64)
    _, _, ok = forward_backward(forward, backward, corners, 1.0)
    assert ok.mean() > 0.8
    # A wrong match: the forward flow around one corner sends it 4 px off.
    wrong = int(np.flatnonzero(ok)[0])
    u, v = np.round(corners[wrong]).astype(int)
    forward[v - 2:v + 3, u - 2:u + 3] += (4.0, 0.0)
    _, error, checked = forward_backward(forward, backward, corners, 1.0)
    assert not checked[wrong] and error[wrong] > 3.0
    far = np.linalg.norm(corners - corners[wrong], axis=1) > 5
    np.testing.assert_array_equal(checked[far], ok[far])


@pytest.mark.parametrize("depth", [True, False])
def test_lifted_particles_of_a_flat_coloured_object_take_its_rendered_colour(depth):
    rest = cube()
    colour = np.array([40.0, 170.0, 60.0])
    frames = reconstruct_recording(recording([rest, rest], np.tile(colour, (len(rest), 1)), depth=depth, lit=True),
                                   ReconstructionConfig())
    assert np.all(frames[0].objects[1].colour == colour)
    lifted = lift_first_complete(frames, LiftingConfig(particle_spacing=0.01))
    assert len(lifted.x) > 0 and np.all(lifted.rgb == colour)
    # and back through the particle cloud
    np.testing.assert_array_equal(type(lifted).from_cloud(lifted.to_cloud()).rgb, lifted.rgb)


def test_lifted_particles_take_the_colour_of_the_texture_under_them():
    rest = cube()
    albedo = checker(rest)
    frames = reconstruct_recording(recording([rest, rest], albedo, depth=True, lit=True), ReconstructionConfig())
    lifted = lift_first_complete(frames, LiftingConfig(particle_spacing=0.01))
    # The particles next to the cube's faces (within a particle spacing): mostly the colour
    # of the texture's nearest rendered particle (a square's edge may fall between them).
    on_face = np.abs(lifted.x - rest.mean(axis=0)).max(axis=1) > SIDE / 2 - 0.01
    nearest = np.argmin(np.linalg.norm(lifted.x[on_face, None] - rest[None], axis=2), axis=1)
    agree = np.all(lifted.rgb[on_face] == albedo[nearest], axis=1)
    assert agree.mean() > 0.6, agree.mean()
