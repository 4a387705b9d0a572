"""The fit's objective around a point of a synthetic recording: what the data pin down, and where.

    python benchmarks/objective_scan.py bags/elastic_on_plastic --at truth \\
        --offset ball=0.004 --offset clay=0.003 --scan ball.nu=0.1,0.2,0.3,0.4 \\
        --out out/objective_scan.json

Builds the fit problem as ``mosiv run`` does (reconstruction, lifting, the first 70 % of the
frames; ``--params-file`` gives the node parameters) and evaluates the identifier's own objective
(``GlobalSearch.batch_object_losses``: Chamfer, silhouette and track terms, mean over the fitted
frames; on the CPU each row at its own stable time step) at a base point, then along one entry at
a time from it (``--scan ball.nu=0.1,0.2``; entries are named as the fit names them: ``ball.E``,
``ground.friction``, ``clay.boundary_offset``).

The base point is the recording's ground truth (``--at truth``: parameters and initial
velocities; boundary offsets 0 unless ``--offset``) or an estimates file (``--at
out/run/estimates.yaml``: parameters, boundary offsets, velocities). ``--set name=value``
overrides an entry, ``--velocity truth`` takes the true initial velocities instead of the
estimated ones (those at the recording's start: refused when lifting started the fit at a later
frame, which the truth gives no velocities for). Two switches ask what the estimated geometry
and the assumed density cost: ``--true-particles`` (all objects, or ``--true-particles cube``)
starts those objects from the recorder's own particles at the fit's first frame instead of the
lifted ones, and ``--density truth`` (or ``--density sand=1600``) simulates objects at their
true density instead of the declared or default one the fit uses. (With identify_node's
``density_ratios`` the fitted densities are entries like any other: ``--set``, ``--scan``.)
``--true-effects`` declares the effects the recording leaves undeclared (the thrown ball's air
drag) at their true values, so that the truth is a point of the fit's model.

A params file with ``loss: {track_weight: 0.0}`` leaves the track term out (the objective with
and without tracks, side by side).

``--centroids`` also rolls every row out over the whole recording and gives its centroid RMS
error on the fitted and on the held-out frames against the reconstruction (the loop closure's
measure, ``loop.residual.analyse``): what the twin predicts at that point, the truth included.
The simulation domain then covers every frame, as the loop's does, so the losses can differ in
the last digits from a scan without it.

Two switches ask what the time step does. ``--common-step`` rolls every row out at one time
step, the stiffest row's (as the search batches rows on a GPU), instead of each at its own
stable one: a scan along a modulus then changes the material alone, not also the substeps.
``--step-scales 1,2,4`` adds rows of the base point at those multiples of its own stable
substeps per frame (entry ``substeps``): how far the objective at one point moves with the
discretisation alone.

Writes JSON: the options, the base point, and per row the whole loss and each object's share.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from mosiv_ros.cli import run_config
from mosiv_ros.config import HOLDOUT
from mosiv_ros.identify.estimates import Estimates
from mosiv_ros.identify.fit import FitSettings, Identifier
from mosiv_ros.identify.problem import build_problem, views_of
from mosiv_ros.identify.run import problem_options
from mosiv_ros.io.files import plain
from mosiv_ros.io.scene import DeclaredEffect, Scene
from mosiv_ros.lifting.lift import LiftedParticles
from mosiv_ros.loop.closure import rollout
from mosiv_ros.loop.observations import Observations
from mosiv_ros.loop.residual import Floor, analyse
from mosiv_ros.pipeline import fit_window
from mosiv_ros.prepare import prepare
from mosiv_ros.sim import BUILTIN_EFFECTS
from mosiv_ros.synth.ground_truth import GroundTruthParticles, read_ground_truth, read_ground_truth_particles


def with_true_particles(lifted: LiftedParticles, truth: GroundTruthParticles,
                        object_ids: list[int]) -> LiftedParticles:
    """``lifted`` with the particles of ``object_ids`` replaced by the recorder's at its stamp."""
    frame = np.flatnonzero(truth.stamps_ns == lifted.stamp_ns)
    if not len(frame):
        raise SystemExit(f"the recording's ground truth has no frame at the lifted stamp {lifted.stamp_ns}")
    volume = np.unique(truth.volume[np.isin(truth.object_id, object_ids)])
    if not np.allclose(volume, lifted.lattice_volume, rtol=1e-4):
        raise SystemExit(f"the recorder's particle volumes {volume} m^3 differ from the lifting's lattice "
                         f"volume {lifted.lattice_volume} m^3: give lifting_node a particle_spacing equal "
                         "to the recording's")
    keep = ~np.isin(lifted.object_id, object_ids)
    parts = {"x": [lifted.x[keep]], "object_id": [lifted.object_id[keep]],
             "segment": [lifted.segment[keep]], "material": [lifted.material[keep]],
             "sdf": [lifted.sdf[keep]]}
    for object_id in object_ids:
        mine = truth.object_id == object_id
        n = int(mine.sum())
        code = lifted.material[lifted.object_id == object_id][0]
        parts["x"].append(truth.positions[frame[0], mine].astype(np.float64))
        parts["object_id"].append(np.full(n, object_id, dtype=lifted.object_id.dtype))
        parts["segment"].append(np.full(n, object_id, dtype=lifted.segment.dtype))
        parts["material"].append(np.full(n, code, dtype=lifted.material.dtype))
        parts["sdf"].append(np.full(n, -1.0))  # deep inside: full volume at any offset
    return dataclasses.replace(lifted, **{key: np.concatenate(value) for key, value in parts.items()})


def with_true_particles_of(lifted: LiftedParticles, bag: Path, which: str,
                           true_objects: dict[str, dict]) -> LiftedParticles:
    """``with_true_particles`` for ``which``: 'all' or comma-separated object names."""
    names = list(true_objects) if which == "all" else which.split(",")
    unknown = sorted(set(names) - set(true_objects))
    if unknown:
        raise SystemExit(f"--true-particles: no object {unknown} (objects: {sorted(true_objects)})")
    return with_true_particles(lifted, read_ground_truth_particles(bag), [true_objects[n]["id"] for n in names])


def asked_densities(items: list[str], true_objects: dict[str, dict]) -> dict[str, float]:
    """``--density`` by object name: ['truth'] (each of ``true_objects`` at its true one) or name=kg/m^3."""
    if items == ["truth"]:
        return {name: float(obj["params"]["density"]) for name, obj in true_objects.items()}
    return {k: float(v) for k, v in pairs(items, "--density").items()}


def declare_densities(values: dict[str, float], objects) -> None:
    """Set each named object's density (objects with ``name`` and ``params``); refuse other names."""
    by_name = {o.name: o for o in objects}
    unknown = sorted(set(values) - set(by_name))
    if unknown:
        raise SystemExit(f"--density: no object {unknown} (objects: {sorted(by_name)})")
    for name, value in values.items():
        by_name[name].params["density"] = value


def declare_true_effects(scene: Scene, truth: dict) -> None:
    """Add the recording's undeclared simulator effects to ``scene``, declared at their true values."""
    undeclared = [e for e in truth.get("effects", []) if not e.get("declared")]
    unknown = [e["type"] for e in undeclared if e["type"] not in BUILTIN_EFFECTS]
    if unknown:
        raise SystemExit(f"--true-effects: {unknown} are not simulator effects "
                         f"(known: {', '.join(sorted(BUILTIN_EFFECTS))})")
    scene.effects.extend(DeclaredEffect(e["type"], dict(e["params"])) for e in undeclared)


def centroid_errors(identifier: Identifier, u: np.ndarray, velocity: np.ndarray, prepared,
                    window: int) -> dict[str, float]:
    """Centroid RMS error (m) of the rollout at ``u`` on the fitted and the held-out frames."""
    identifier.apply(u, velocity)
    prediction = rollout(identifier, Observations(prepared.frames, prepared.lifted))
    return analyse(prepared.frames, prediction, window, Floor.of(prepared.recording.scene)).errors()


def pairs(items: list[str], what: str) -> dict[str, str]:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"{what} {item!r}: expected name=value")
        out[name] = value
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bag", type=Path)
    parser.add_argument("--at", default="truth", help="'truth' or an estimates YAML file")
    parser.add_argument("--scan", action="append", default=[], help="entry=v1,v2,... (repeatable)")
    parser.add_argument("--set", action="append", default=[], help="entry=value (repeatable)")
    parser.add_argument("--offset", action="append", default=[], help="object=metres (repeatable)")
    parser.add_argument("--velocity", choices=("base", "truth"), default="base")
    parser.add_argument("--true-particles", nargs="?", const="all", default="",
                        help="'all' or comma-separated object names")
    parser.add_argument("--density", action="append", default=[], help="'truth' or object=kg/m^3")
    parser.add_argument("--true-effects", action="store_true",
                        help="declare the recording's undeclared effects at their true values")
    parser.add_argument("--params-file", type=Path, default=Path("config/demo.yaml"))
    parser.add_argument("--holdout", type=float, default=HOLDOUT)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--centroids", action="store_true",
                        help="also give each row's centroid error on the fitted and held-out frames")
    parser.add_argument("--common-step", action="store_true",
                        help="every row at the stiffest row's time step, not each at its own")
    parser.add_argument("--step-scales", default="",
                        help="multiples of the base point's stable substeps to roll it out at, e.g. 1,2,4")
    parser.add_argument("--out", type=Path, default=Path("out/objective_scan.json"))
    args = parser.parse_args()

    truth = read_ground_truth(args.bag)
    true_objects = {o["name"]: o for o in truth["objects"]}
    config = run_config(args.params_file, args.device)
    prepared = prepare(args.bag, config)
    if args.true_effects:
        declare_true_effects(prepared.recording.scene, truth)
    lifted = prepared.lifted
    if args.true_particles:
        lifted = with_true_particles_of(lifted, args.bag, args.true_particles, true_objects)
    window = fit_window(len(prepared.frames), args.holdout)
    views = views_of(prepared.recording)
    simulated = prepared.frames if args.centroids else prepared.frames[:window]
    problem = build_problem(simulated, lifted, prepared.recording.scene, views,
                            prepared.recording.gripper_poses, problem_options(config.identify, views))
    if args.centroids:
        problem.observations = problem.observations.select(slice(0, window))
    problem.sim_config.device = args.device
    declare_densities(asked_densities(args.density, {o.name: true_objects[o.name] for o in problem.objects}),
                      problem.objects)
    identifier = Identifier(problem, FitSettings.of(config.identify))
    labels = [entry.label for entry in identifier.entries]

    # the base point: parameters, offsets and velocities
    values = {"ground.friction": truth["ground"]["friction"]} if truth.get("ground") else {}
    for name, obj in true_objects.items():
        values.update({f"{name}.{k}": v for k, v in obj["params"].items()})
    velocity = {name: list(obj["velocity"]) + list(obj["angular_velocity"])
                for name, obj in true_objects.items()}
    estimated = set()
    if args.at != "truth":
        estimates = Estimates.read(args.at)
        values.update(estimates.scene)
        for obj in estimates.objects:
            values.update({f"{obj.name}.{k}": v for k, v in obj.params.items()})
            if args.velocity == "base":
                velocity[obj.name] = list(obj.velocity)
                estimated.add(obj.name)
    start = int(truth["frames"]["start_stamp_ns"])
    if lifted.stamp_ns != start and any(obj.name not in estimated for obj in problem.objects):
        raise SystemExit(f"the true initial velocities are the recording's at its start ({start} ns), but the "
                         f"fit starts at {lifted.stamp_ns} ns, the first frame lifting could use: give "
                         "--at an estimates file, whose velocities are at the fit's start")
    values.update({f"{k}.boundary_offset": float(v) for k, v in pairs(args.offset, "--offset").items()})
    values.update({k: float(v) for k, v in pairs(args.set, "--set").items()})
    missing = [label for label in labels if label not in values and not label.endswith(".boundary_offset")]
    if missing:
        raise SystemExit(f"no base value for {missing}: give them with --set")
    base = np.array([e.coordinate.to_u(values.get(e.label, 0.0)) for e in identifier.entries])
    v0 = np.array([velocity[obj.name] for obj in problem.objects], dtype=np.float64)

    rows, named = [base], [(None, None)]
    for name, listed in pairs(args.scan, "--scan").items():
        if name not in labels:
            raise SystemExit(f"--scan {name}: not a fitted entry of this problem ({', '.join(labels)})")
        i = labels.index(name)
        for value in map(float, listed.split(",")):
            row = base.copy()
            row[i] = identifier.entries[i].coordinate.to_u(value)
            rows.append(row)
            named.append((name, value))
    print(f"{len(rows)} rows over {window - 1} frames on {args.device} ...", flush=True)
    tick = time.perf_counter()
    search = identifier.search
    total, per = search.batch_object_losses(np.array(rows), v0, together=args.common_step or None)
    if args.step_scales:
        identifier.apply(base, v0)
        stable = identifier.sim.time_step()[0]
        for scale in map(float, args.step_scales.split(",")):
            substeps = max(stable, round(scale * stable))
            t, p = search.batch_object_losses(base[None], v0, substeps=substeps)
            total, per = np.concatenate([total, t]), np.concatenate([per, p])
            named.append(("substeps", substeps))
    seconds = time.perf_counter() - tick
    names = [obj.name for obj in problem.objects]
    results = [{"entry": entry, "value": value, "loss": float(t),
                "objects": dict(zip(names, map(float, p), strict=True))}
               for (entry, value), t, p in zip(named, total, per, strict=True)]
    if args.centroids:
        for r, row in zip(results[:len(rows)], rows, strict=True):  # not the step-scale rows
            r["centroid_error"] = centroid_errors(identifier, row, v0, prepared, window)
    print(f"{'entry':28s} {'value':>10s} {'loss x1e5':>10s}  " + " ".join(f"{n:>9s}" for n in names)
          + ("  centroid error fitted / held-out (mm)" if args.centroids else ""))
    for r in results:
        value = "" if r["value"] is None else f"{r['value']:g}"
        errors = r.get("centroid_error")
        print(f"{r['entry'] or 'base':28s} {value:>10s} {r['loss'] * 1e5:10.2f}  "
              + " ".join(f"{v * 1e5:9.2f}" for v in r["objects"].values())
              + (f"  {errors['fitted'] * 1e3:.2f} / {errors['held_out'] * 1e3:.2f}" if errors else ""))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(plain({
        "benchmark": "objective_scan", "bag": str(args.bag), "device": args.device,
        "host": platform.node(), "python": sys.version.split()[0], "argv": sys.argv[1:],
        "frames": window, "particles": {n: int((identifier.index == k).sum()) for k, n in enumerate(names)},
        "density": {obj.name: obj.params.get("density") for obj in problem.objects},
        "base": {label: values.get(label, 0.0) for label in labels},
        "velocity": dict(zip(names, v0.tolist(), strict=True)), "seconds": seconds, "rows": results},
        null_nonfinite=True), indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
