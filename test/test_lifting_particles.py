"""Stage 2: particles per object, volumes, thin parts, non-overlapping support, M-PhyGs volumes."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from recon_scenes import sphere_recording, touching_pair
from scipy.spatial import cKDTree

from mosiv_ros.config import LiftingConfig, ReconstructionConfig
from mosiv_ros.io.messages import pointcloud_from_msg, pointcloud_to_msg, rosbags_types
from mosiv_ros.io.recording import PointCloud
from mosiv_ros.io.scene import FAMILIES, Scene, SceneObject
from mosiv_ros.lifting import LiftedParticles, border_note, boundary_volume, lift, lift_choice, lift_first_complete
from mosiv_ros.recon import VOXEL_FIELD, ObjectGeometry, ObservedFrame, cut_objects, reconstruct_recording

VOXEL = 0.005
FINE = LiftingConfig(particle_spacing=0.004)  # a lattice finer than the voxels
H = FINE.particle_spacing
SCENE = Scene(objects=[SceneObject(1, "a", "elastic"), SceneObject(2, "b", "sand")])


def voxelised(inside, lo, hi, voxel: float = VOXEL) -> np.ndarray:
    """Centres of the voxels (world-aligned lattice) whose centre satisfies ``inside``."""
    axes = [voxel * (np.arange(np.floor(lo[a] / voxel), np.ceil(hi[a] / voxel)) + 0.5) for a in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return centres[inside(centres)]


def ball(centre, radius):
    centre = np.asarray(centre, float)
    return voxelised(lambda p: np.linalg.norm(p - centre, axis=1) <= radius, centre - radius, centre + radius)


def observed(*objects: np.ndarray, voxel: float = VOXEL) -> PointCloud:
    """An observed cloud with the voxel centres of each object (ids 1, 2, ...)."""
    xyz = np.concatenate(objects)
    ids = np.concatenate([np.full(len(o), k + 1) for k, o in enumerate(objects)])
    return PointCloud(xyz, ids, {VOXEL_FIELD: np.full(len(xyz), voxel, np.float32)}, stamp_ns=7)


@pytest.mark.parametrize("radius", [0.03, 0.06, 0.1])
def test_lifted_volume_of_a_ball_is_within_3_percent_of_its_true_volume(radius):
    lifted = lift(observed(ball((0.01, -0.02, 0.2), radius)), FINE, SCENE)
    true = 4 / 3 * math.pi * radius**3
    assert abs(lifted.object_volume(1) / true - 1) < 0.03
    assert np.all(lifted.material == FAMILIES.index("elastic"))


def test_a_one_voxel_thin_plate_and_rod_are_not_eroded():
    plate = voxelised(lambda p: np.ones(len(p), bool), (0.0, 0.0, 0.1), (0.1, 0.1, 0.1 + VOXEL))
    rod = voxelised(lambda p: np.ones(len(p), bool), (0.2, 0.0, 0.1), (0.2 + VOXEL, VOXEL, 0.2))
    thin = np.concatenate([plate, rod])
    # On the voxels' own lattice the refined shape is exactly the observed one.
    same = lift(observed(thin), LiftingConfig(particle_spacing=VOXEL), SCENE)
    np.testing.assert_allclose(same.object_volume(1), len(thin) * VOXEL**3, rtol=1e-3)
    # On a finer lattice every observed voxel still holds solid particles.
    lifted = lift(observed(thin), FINE, SCENE)
    solid = lifted.x[lifted.sdf <= 0]
    distance, _ = cKDTree(solid).query(thin, p=np.inf)
    assert np.all(distance <= VOXEL / 2)


def test_on_a_lattice_coarser_than_the_voxels_volumes_hold_and_thin_parts_stay_one_cell_thick():
    coarse = LiftingConfig(particle_spacing=0.01)
    lifted = lift(observed(ball((0.01, -0.02, 0.2), 0.05)), coarse, SCENE)
    assert abs(lifted.object_volume(1) / (4 / 3 * math.pi * 0.05**3) - 1) < 0.1
    plate = voxelised(lambda p: np.ones(len(p), bool), (0.0, 0.0, 0.1), (0.1, 0.1, 0.1 + VOXEL))
    thin = lift(observed(plate), coarse, SCENE)
    solid = thin.x[thin.sdf <= 0]
    assert len(solid) and np.all(cKDTree(solid).query(plate, p=np.inf)[0] <= 0.01)
    assert np.ptp(solid[:, 2]) < 1e-9  # one cell thick, not grown


@pytest.mark.parametrize("shift", [0.0, VOXEL])
def test_on_a_lattice_coarser_than_the_voxels_a_box_is_lifted_where_it_is(shift):
    # With shift = one voxel every face lies on cell centres: each face cell is half covered,
    # and the volume and centre must not depend on how such ties fall.
    lo, hi = np.array([0.0, 0.0, 0.1]) + shift, np.array([0.06, 0.04, 0.16]) + shift
    box = voxelised(lambda p: np.ones(len(p), bool), lo, hi)
    lifted = lift(observed(box), LiftingConfig(particle_spacing=0.01), SCENE)
    volumes = lifted.volumes()
    centre = (volumes[:, None] * lifted.x).sum(axis=0) / volumes.sum()
    np.testing.assert_allclose(centre, (lo + hi) / 2, atol=1e-3)
    assert abs(volumes.sum() / np.prod(hi - lo) - 1) < 0.1


def test_on_a_lattice_coarser_than_the_voxels_signed_distances_follow_the_voxels():
    centre, radius = np.array([0.01, -0.02, 0.2]), 0.04
    lifted = lift(observed(ball(centre, radius)), LiftingConfig(particle_spacing=0.01), SCENE)
    solid = lifted.sdf <= 0
    true = np.linalg.norm(lifted.x - centre, axis=1) - radius  # to the ball, negative inside
    near = solid & (true > -0.01)
    # to within a voxel, not a cell (every outermost cell at -h/2 would be up to 1 cm off)
    assert near.sum() > 50
    assert np.abs(lifted.sdf[near] - np.minimum(true[near], 0.0)).max() <= VOXEL
    # so the boundary offset moves the surface in sub-cell steps: the lifted volume changes
    # smoothly with it instead of a whole layer at a time
    true_volume = 4 / 3 * math.pi * radius**3
    volumes = [lifted.object_volume(1, {1: o}) / true_volume for o in np.arange(0.0, 0.0051, 0.001)]
    assert np.all(np.diff(volumes) < 0) and np.all(-np.diff(volumes) < 0.25)


def test_density_refinement_fills_a_pinhole_and_a_one_cell_crack():
    cube = voxelised(lambda p: np.ones(len(p), bool), (0.0, 0.0, 0.0), (0.06, 0.06, 0.06))
    pinhole = np.all(np.isclose(cube, [0.0325, 0.0325, 0.0325]), axis=1)
    inner = np.all((cube[:, 1:] > 0.015) & (cube[:, 1:] < 0.045), axis=1)
    crack = np.isclose(cube[:, 0], 0.0175) & inner  # a one-cell-thick fissure inside the cube
    holed = cube[~pinhole & ~crack]
    lifted = lift(observed(holed), LiftingConfig(particle_spacing=VOXEL), SCENE)
    solid = lifted.x[lifted.sdf <= 0]
    assert cKDTree(solid).query([0.0325, 0.0325, 0.0325])[0] < 1e-6
    assert np.all(cKDTree(solid).query(cube[crack])[0] < 1e-6)
    unrefined = lift(observed(holed), LiftingConfig(particle_spacing=VOXEL, density_iterations=0), SCENE)
    assert cKDTree(unrefined.x[unrefined.sdf <= 0]).query([0.0325, 0.0325, 0.0325])[0] > 1e-3


def test_interpenetrating_objects_get_disjoint_supports_split_between_them():
    a, b = ball((0.0, 0.0, 0.1), 0.05), ball((0.08, 0.0, 0.1), 0.05)  # overlapping by 2 cm
    lifted = lift(observed(a, b), FINE, SCENE)
    cells = np.floor(lifted.x / H).astype(np.int64)
    _, counts = np.unique(cells, axis=0, return_counts=True)
    assert counts.max() == 1
    xa, xb = lifted.x[lifted.object_id == 1], lifted.x[lifted.object_id == 2]
    assert cKDTree(xb).query(xa)[0].min() >= H * (1 - 1e-9)
    # The lens goes half to each (equal balls): the interface is the bisecting plane x = 4 cm.
    solid_a = xa[lifted.sdf[lifted.object_id == 1] <= 0]
    solid_b = xb[lifted.sdf[lifted.object_id == 2] <= 0]
    assert solid_a[:, 0].max() < 0.04 + H and solid_b[:, 0].min() > 0.04 - H
    assert abs(lifted.object_volume(1) / lifted.object_volume(2) - 1) < 0.03
    # Band particles never reach into the other object: those of a near b are outside b's solid.
    assert np.all(lifted.sdf[lifted.object_id == 1][xa[:, 0] > 0.04] > -H)
    # The solid at per-object offsets: each object's surface moves by its own o_s only.
    solid = lifted.solid({1: 0.004, 2: -0.003})
    for i, offset in ((1, 0.004), (2, -0.003)):
        mine = lifted.object_id == i
        np.testing.assert_array_equal(solid[mine], lifted.sdf[mine] <= -offset)
    assert solid[lifted.object_id == 1].sum() < (lifted.sdf[lifted.object_id == 1] <= 0).sum()


def test_touching_objects_lifted_from_reconstruction_keep_their_volume_and_never_overlap():
    spheres = touching_pair()
    frames = reconstruct_recording(sphere_recording(spheres), ReconstructionConfig())
    lifted = lift_first_complete(frames, FINE, frames and _scene(spheres))
    for s in spheres:
        true = 4 / 3 * math.pi * s.radius**3
        assert abs(lifted.object_volume(s.id) / true - 1) < 0.08, s.name
        assert lifted.families[s.id] == s.family
    cells = np.floor(lifted.x / H).astype(np.int64)
    assert np.unique(cells, axis=0).shape[0] == len(cells)
    left, right = spheres[0], spheres[1]
    solid_left = lifted.x[(lifted.object_id == left.id) & (lifted.sdf <= 0)]
    assert np.all(np.linalg.norm(solid_left - right.centre(0.0), axis=1) > right.radius - H)


def test_boundary_volumes_follow_the_mphygs_sigmoid_and_the_offsets():
    lifted = lift(observed(ball((0.0, 0.0, 0.1), 0.05)), FINE, SCENE)
    config = FINE
    V_g = H**3
    expected = V_g * (1 / (1 + np.exp(config.boundary_beta * lifted.sdf)) + config.boundary_eps)
    np.testing.assert_allclose(lifted.volumes(), expected, rtol=1e-9)
    assert lifted.sdf.max() < config.boundary_band and lifted.sdf.min() < -0.04
    band = lifted.sdf > 0
    assert band.sum() > 0 and np.all(lifted.volumes()[band] < V_g * 0.2)
    # o_s > 0 moves the boundary inwards (less volume), o_s < 0 outwards into the band.
    base = lifted.object_volume(1)
    assert lifted.object_volume(1, {1: 0.004}) < base < lifted.object_volume(1, {1: -0.004})
    np.testing.assert_allclose(boundary_volume(np.array([0.0]), V_g, 0.0, 5e3, 1e-4), V_g * (0.5 + 1e-4))


def test_particle_cloud_round_trips_through_pointcloud2():
    lifted = lift(observed(ball((0.0, 0.0, 0.1), 0.03), ball((0.1, 0.0, 0.1), 0.02)), FINE, SCENE)
    cloud = lifted.to_cloud()
    msg = pointcloud_to_msg(rosbags_types(), cloud.xyz, cloud.object_id, cloud.stamp_ns, "world", cloud.fields)
    assert [f.name for f in msg.fields] == ["x", "y", "z", "object_id", "volume", "material", "sdf",
                                            "lattice_volume", "segment", "boundary_beta", "boundary_eps"]
    back = LiftedParticles.from_cloud(pointcloud_from_msg(msg))
    assert (back.beta, back.eps) == (lifted.beta, lifted.eps)
    assert back.segment.dtype == np.uint16 and back.material.dtype == np.uint8
    np.testing.assert_array_equal(back.object_id, lifted.object_id)
    families = np.where(back.object_id == 1, FAMILIES.index("elastic"), FAMILIES.index("sand"))
    np.testing.assert_array_equal(back.material, families)
    np.testing.assert_allclose(back.x, lifted.x, atol=1e-7)
    np.testing.assert_allclose(back.volumes(), lifted.volumes(), rtol=1e-5)
    assert back.stamp_ns == 7


def test_an_empty_particle_cloud_is_refused_saying_so():
    cloud = lift(observed(ball((0.0, 0.0, 0.1), 0.03)), FINE, SCENE).to_cloud()
    empty = PointCloud(cloud.xyz[:0], cloud.object_id[:0], {k: v[:0] for k, v in cloud.fields.items()},
                       stamp_ns=7)
    with pytest.raises(ValueError, match="particle cloud of stamp 7 ns is empty: no particle to simulate"):
        LiftedParticles.from_cloud(empty)


def test_an_undeclared_object_is_lifted_with_unknown_material_and_a_warning():
    lifted = lift(observed(ball((0.0, 0.0, 0.1), 0.03)), FINE, Scene())
    assert np.all(lifted.material == 255)
    assert any("not declared" in w for w in lifted.warnings)


def test_lifting_waits_for_the_first_frame_with_every_declared_object():
    a, b = ball((0.0, 0.0, 0.1), 0.03), ball((0.1, 0.0, 0.1), 0.02)

    def frame(stamp, *objects):
        geometry = {i: ObjectGeometry(i, pts, np.zeros((0, 3)), VOXEL) for i, pts in objects}
        return ObservedFrame(stamp, geometry)

    frames = [frame(1, (1, a)), frame(2, (1, a), (2, b)), frame(3, (2, b))]
    lifted = lift_first_complete(frames, FINE, SCENE)
    assert lifted.stamp_ns == 2 and lifted.object_ids == [1, 2]
    with pytest.raises(ValueError, match="every declared object"):
        lift_first_complete(frames[:1], FINE, SCENE)


def test_lifting_takes_the_first_frame_that_no_image_border_cuts_within_border_wait():
    a, b = ball((0.0, 0.0, 0.1), 0.03), ball((0.1, 0.0, 0.1), 0.02)

    def frame(stamp, cut=()):
        geometry = {i: ObjectGeometry(i, pts, np.zeros((0, 3)), VOXEL) for i, pts in ((1, a), (2, b))}
        return ObservedFrame(stamp, geometry, cut={i: ("cam0",) for i in cut})

    frames = [frame(1, cut=[2]), frame(2, cut=[2]), frame(3), frame(4)]
    clouds = [f.to_cloud() for f in frames]
    assert cut_objects(clouds[0]) == [2] and cut_objects(clouds[2]) == []
    assert ObservedFrame.from_cloud(clouds[0]).cut == {2: ()}  # the cloud carries the cut, not the cameras
    assert lift_first_complete(frames, FINE, SCENE).stamp_ns == 3
    assert lift_first_complete(frames, replace(FINE, border_wait=1), SCENE).stamp_ns == 1  # not waited for
    assert lift_first_complete(frames[:2], FINE, SCENE).stamp_ns == 1  # none whole: the first complete
    # as lifting_node decides, cloud by cloud: wait while every cloud so far is cut
    assert lift_choice(clouds[:1], SCENE, 5) is None and lift_choice(clouds[:2], SCENE, 5) is None
    assert lift_choice(clouds[:3], SCENE, 5) == 2
    assert lift_choice(clouds[:2], SCENE, 1) == 0  # waited border_wait frames: the first
    # the warning both say: which stamp is lifted instead, or that the cut one is lifted as it is
    assert border_note(clouds, 2) == ("stamp 1 ns: an image border cuts objects [2]; lifting stamp 3 ns, "
                                      "which shows them whole")
    assert "without their parts beyond the border" in border_note(clouds, 0)
    assert border_note(clouds[2:], 0) is None


def test_lifting_rejects_a_cloud_without_voxels_clearly():
    with pytest.raises(ValueError, match="voxel_size"):
        lift(PointCloud(np.zeros((3, 3)), np.ones(3), stamp_ns=5), FINE, SCENE)


def _scene(spheres) -> Scene:
    return Scene(objects=[SceneObject(s.id, s.name, s.family) for s in spheres])
