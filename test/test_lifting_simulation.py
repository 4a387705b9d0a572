"""Lifted particles feed the simulator directly, with the identifier's boundary offsets."""

from __future__ import annotations

import numpy as np

from mosiv_ros.config import LiftingConfig
from mosiv_ros.io.recording import PointCloud
from mosiv_ros.io.scene import FAMILIES, Scene, SceneObject
from mosiv_ros.lifting import lift
from mosiv_ros.recon import VOXEL_FIELD
from mosiv_ros.sim import Ground, ObjectModel, SimConfig, Simulator, domain_around
from mosiv_ros.sim.materials import FAMILY_CODES
from mosiv_ros.sim.sampling import box
from mosiv_ros.simulation import to_sim_particles

SPACING = 0.01


def test_material_codes_are_the_simulators_family_codes():
    assert {family: FAMILIES.index(family) for family in FAMILIES} == FAMILY_CODES


def test_two_lifted_blocks_run_in_the_simulator_with_per_segment_offsets():
    lower, _ = box((0.0, 0.0, 0.05), (0.06, 0.06, 0.03), 0.005)
    upper, _ = box((0.0, 0.0, 0.11), (0.03, 0.03, 0.03), 0.005)
    xyz = np.concatenate([lower, upper])
    ids = np.repeat([3, 5], [len(lower), len(upper)])
    cloud = PointCloud(xyz, ids, {VOXEL_FIELD: np.full(len(xyz), 0.005, np.float32)})
    scene = Scene(objects=[SceneObject(3, "slab", "plastic"), SceneObject(5, "block", "elastic")])
    lifted = lift(cloud, LiftingConfig(particle_spacing=SPACING, boundary_band=2 * SPACING), scene)

    particles, order = to_sim_particles(lifted, {5: 0.004})
    assert order == [3, 5]
    np.testing.assert_array_equal(particles.object_index, (lifted.object_id == 5).astype(int))
    assert np.all(particles.volume > 0)
    shifted = particles.volume[particles.object_index == 1].sum()
    assert shifted < lifted.object_volume(5)  # o_s > 0 shrinks segment 5 only
    np.testing.assert_allclose(particles.volume[particles.object_index == 0].sum(), lifted.object_volume(3))

    objects = [ObjectModel("slab", "plastic", {"E": 1e5}, id=3), ObjectModel("block", "elastic", {"E": 1e5}, id=5)]
    lo, hi = domain_around(particles.x, 2 * SPACING, floor=0.0)
    sim = Simulator(objects, particles, SimConfig(dx=2 * SPACING, lo=lo, hi=hi, ground=Ground(height=0.0),
                                                  device="cpu"))
    x = sim.rollout(2)
    assert x.shape == (3, 1, len(particles.x), 3) and np.all(np.isfinite(x))
