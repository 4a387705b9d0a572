"""Stage 1-2 figures on synthetic recordings: per-object Chamfer per frame, lifted volumes, timing.

    python benchmarks/recon_figures.py /path/to/bag [...]  [--out figures.json] [--voxel-size 0.005]
    python benchmarks/recon_figures.py --shapes        # the analytic shapes scene, 4 cameras 160x120

For every bag with the recorder's ``ground_truth_particles.npz`` sidecar (or the analytic spheres
of ``mosiv_ros.synth.shapes``, as 3 mm lattice particles filling each ball), reconstruct every frame
with and without depth and print, per object and frame, the Chamfer distance (mm; the mean of the
two one-sided mean nearest-neighbour distances, ``mosiv_ros.metrics``) between the
object's occupied voxel centres and its ground-truth particles, and as a fraction of the object's
size (largest edge of the particles' bounding box plus one particle). ``floor`` is the same
distance for a perfect reconstruction: the voxels whose centres lie in the cubes the ground-truth
particles stand for. ``nearer other`` is the largest fraction, over frames, of an object's voxels
that lie nearer another object's particles than its own (separation at contact). Then lift the
first complete frame and print each object's particle volume against the ground-truth volume and
against the volume the recorder renders (the union of its splat balls above the floor: what the
cameras can see; the balls themselves for the shapes scene), the lattice cells shared between
objects (must be 0) and the milliseconds per frame of both stages on this machine. Surface
tracks, with and without depth: per object and frame the tracks alive and the median 3D error
(mm) of their motion since their first frame against the ground truth's
(``mosiv_ros.recon.evaluation.track_errors``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from mosiv_ros.config import LiftingConfig, ReconstructionConfig
from mosiv_ros.io.bag import read_recording
from mosiv_ros.lifting import lift_first_complete
from mosiv_ros.metrics import chamfer_distance
from mosiv_ros.recon import SurfaceTracks, reconstruct_recording
from mosiv_ros.recon.carving import Lattice
from mosiv_ros.recon.evaluation import track_errors, union_of_balls_volume
from mosiv_ros.recon.reconstruct import Reconstructor
from mosiv_ros.synth.ground_truth import GroundTruthParticles, read_ground_truth, read_ground_truth_particles
from mosiv_ros.synth.shapes import START_NS, make_shapes_recording, shapes_spheres

SHAPES_SPACING = 0.003


def perfect_voxels(truth: np.ndarray, side: float, lattice: Lattice) -> np.ndarray:
    """Voxel centres of ``lattice`` inside the cubes of edge ``side`` around the truth particles."""
    lo = np.floor((truth.min(axis=0) - side - lattice.origin) / lattice.voxel_size).astype(int)
    hi = np.ceil((truth.max(axis=0) + side - lattice.origin) / lattice.voxel_size).astype(int)
    axes = [np.arange(lo[a], hi[a]) for a in range(3)]
    centres = lattice.centres(np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3))
    distance, _ = cKDTree(truth).query(centres, p=np.inf)
    return centres[distance <= side / 2]


def shapes_truth(recording) -> GroundTruthParticles:
    """The shapes scene's balls as lattice particles at every frame of ``recording``."""
    stamps = np.array(next(iter(recording.cameras.values())).stamps_ns)
    times = (stamps - START_NS) * 1e-9
    positions, ids = [], []
    for sphere in shapes_spheres():
        n = int(np.ceil(sphere.radius / SHAPES_SPACING))
        axis = np.arange(-n, n + 1) * SHAPES_SPACING
        offsets = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
        offsets = offsets[np.linalg.norm(offsets, axis=1) <= sphere.radius]
        positions.append(np.stack([sphere.centre(t) + offsets for t in times]))
        ids.append(np.full(len(offsets), sphere.id))
    object_id = np.concatenate(ids)
    return GroundTruthParticles(np.concatenate(positions, axis=1), object_id,
                                np.full(len(object_id), SHAPES_SPACING**3), stamps, times)


def bag_figures(bag: Path, voxel_size: float) -> dict:
    return figures(str(bag), read_recording(bag), read_ground_truth_particles(bag), voxel_size,
                   float(read_ground_truth(bag)["render"]["splat_radius"]))


def shapes_figures(voxel_size: float) -> dict:
    recording = make_shapes_recording(n_frames=10, n_cameras=4, width=160, height=120)
    return figures("shapes (4 cameras, 160x120)", recording, shapes_truth(recording), voxel_size, None)


def figures(name: str, recording, truth: GroundTruthParticles, voxel_size: float,
            splat: float | None) -> dict:
    """Every figure of one recording; ``splat``: the recorder's splat radius (None: exact shapes)."""
    side = float(np.cbrt(np.median(truth.volume)))
    result: dict = {"bag": name, "voxel_size": voxel_size, "objects": {}, "ms_per_frame": {}}
    for use_depth in (False, True):
        config = ReconstructionConfig(voxel_size=voxel_size, use_depth=use_depth)
        start = time.perf_counter()
        frames = reconstruct_recording(recording, config)
        result["ms_per_frame"][f"reconstruct depth={use_depth}"] = (time.perf_counter() - start) / len(frames) * 1e3
        lattice = Reconstructor(recording.cameras, config, recording.scene).lattice
        result.setdefault("tracks", {})[f"depth={use_depth}"] = track_figures(frames, truth)
        for frame in frames:
            index = int(np.argmin(np.abs(truth.stamps_ns - frame.stamp_ns)))
            trees = {i: cKDTree(truth.of_object(i)[index]) for i in recording.scene.ids}
            for object_id in recording.scene.ids:
                points = truth.of_object(object_id)[index].astype(np.float64)
                size = float(np.max(points.max(axis=0) - points.min(axis=0))) + side
                estimate = frame.objects.get(object_id)
                cd = chamfer_distance(estimate.occupancy, points) if estimate is not None else float("inf")
                nearer = 0.0
                if estimate is not None and len(trees) > 1:
                    own = trees[object_id].query(estimate.occupancy)[0]
                    other = np.min([t.query(estimate.occupancy)[0] for i, t in trees.items() if i != object_id],
                                   axis=0)
                    nearer = float(np.mean(other < own))
                row = result["objects"].setdefault(str(object_id), {}).setdefault(
                    f"depth={use_depth}", [])
                floor = chamfer_distance(perfect_voxels(points, side, lattice), points)
                row.append({"frame": index, "cd_mm": cd * 1e3, "relative": cd / size,
                            "floor_mm": floor * 1e3, "nearer_other": nearer, "warnings": len(frame.warnings)})
        if use_depth:
            start = time.perf_counter()
            lifted = lift_first_complete(frames, LiftingConfig(), recording.scene)
            result["ms_per_frame"]["lift"] = (time.perf_counter() - start) * 1e3
            first = int(np.argmin(np.abs(truth.stamps_ns - lifted.stamp_ns)))
            cells = np.floor(lifted.x / LiftingConfig().particle_spacing).astype(np.int64)
            _, counts = np.unique(cells, axis=0, return_counts=True)
            floor = recording.scene.ground.height if recording.scene.ground else None
            result["lift"] = {"shared_cells": int((counts > 1).sum()), "frame": first, "objects": {
                str(i): {"particles": int((lifted.object_id == i).sum()),
                         "volume_cm3": lifted.object_volume(i) * 1e6,
                         "true_cm3": float(truth.volume[truth.object_id == i].sum()) * 1e6,
                         "rendered_cm3": (union_of_balls_volume(
                             truth.of_object(i)[first].astype(np.float64), splat, floor) * 1e6 if splat
                             else _ball_volume(i) * 1e6)}
                for i in lifted.object_ids}}
    return result


def track_figures(frames, truth: GroundTruthParticles) -> dict:
    """Per object: tracks alive and their median error (mm) per frame (None where none is alive)."""
    tracks = SurfaceTracks.of([frame.tracks for frame in frames])
    index = [int(np.argmin(np.abs(truth.stamps_ns - stamp))) for stamp in tracks.stamps_ns]
    errors = track_errors(tracks, truth.positions[index].astype(np.float64), truth.object_id)
    figures = {}
    for object_id in np.unique(tracks.object_id).tolist():
        mine = errors[:, tracks.object_id == object_id]
        figures[str(object_id)] = {
            "alive": np.isfinite(mine).sum(axis=1).tolist(),
            "median_mm": [float(np.median(row[np.isfinite(row)])) * 1e3 if np.isfinite(row).any() else None
                          for row in mine]}
    return figures


def _ball_volume(object_id: int) -> float:
    radius = next(s.radius for s in shapes_spheres() if s.id == object_id)
    return 4.0 / 3.0 * np.pi * radius**3


def report(result: dict) -> None:
    print(f"\n{result['bag']} (voxel {result['voxel_size'] * 1e3:.1f} mm)")
    for object_id, runs in result["objects"].items():
        for run, rows in runs.items():
            cd = np.array([r["cd_mm"] for r in rows])
            rel = np.array([r["relative"] for r in rows])
            floor = np.array([r["floor_mm"] for r in rows])
            nearer = max(r["nearer_other"] for r in rows)
            print(f"  object {object_id} {run}: CD mm mean {cd.mean():.2f} max {cd.max():.2f} "
                  f"(relative mean {rel.mean() * 100:.1f}% max {rel.max() * 100:.1f}%), "
                  f"floor mean {floor.mean():.2f} mm, nearer other max {nearer * 100:.1f}%")
            print("    per frame CD mm: " + " ".join(f"{v:.1f}" for v in cd))
    lifted = result.get("lift", {})
    for object_id, row in lifted.get("objects", {}).items():
        print(f"  lifted object {object_id}: {row['particles']} particles, {row['volume_cm3']:.1f} cm^3 "
              f"vs true {row['true_cm3']:.1f} cm^3 ({(row['volume_cm3'] / row['true_cm3'] - 1) * 100:+.1f}%), "
              f"vs rendered {row['rendered_cm3']:.1f} cm^3 "
              f"({(row['volume_cm3'] / row['rendered_cm3'] - 1) * 100:+.1f}%)")
    print(f"  lattice cells shared between objects: {lifted.get('shared_cells')}")
    for run, objects in result.get("tracks", {}).items():
        for object_id, row in objects.items():
            median = [m for m in row["median_mm"] if m is not None]
            print(f"  tracks {run} object {object_id}: alive {row['alive'][0]} at frame 0, "
                  f"{min(row['alive'])}-{max(row['alive'])} per frame; median error mm, last frame "
                  f"{median[-1]:.1f}, largest {max(median):.1f}")
            print("    per frame median mm: " + " ".join(f"{m:.1f}" for m in median))
    print("  ms per frame: " + ", ".join(f"{k} {v:.0f}" for k, v in result["ms_per_frame"].items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bags", nargs="*", type=Path)
    parser.add_argument("--shapes", action="store_true", help="also the analytic shapes scene")
    parser.add_argument("--voxel-size", type=float, default=ReconstructionConfig().voxel_size)
    parser.add_argument("--out", type=Path, default=None, help="write every figure as JSON here")
    args = parser.parse_args()
    results = [bag_figures(bag, args.voxel_size) for bag in args.bags]
    if args.shapes:
        results.append(shapes_figures(args.voxel_size))
    for result in results:
        report(result)
    if args.out:
        args.out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
