"""``mosiv batch DIR... --out OUT``: the pipeline (and the loop closure) on many recordings, with Ray.

``run_batch(paths, out, config, batch)`` finds every rosbag2 directory under ``paths``
(``io.bag.find_bags``) and runs each as one Ray task: ``mosiv run`` (``pipeline``) and, with
``batch.close_loop``, ``mosiv close-loop`` (``loop.report``) on the same reconstruction. A task
asks Ray for one GPU when the simulation device is CUDA ('auto': when the cluster has GPUs),
else for the CPU cores its fit uses (identify_node's ``cpu_workers``; its 0, every core, is one
core here, so that recordings run side by side). Ray runs on this machine (``ray.init()``, all
its cores and GPUs, or ``batch.cpus``) unless ``batch.address`` names a cluster to join; on a
cluster, every node must import ``mosiv_ros`` and see the recordings and ``out`` at the same paths.

``out`` holds a folder per recording (its name: the bag's path below the directory given, with
``__`` for ``/``): ``run/`` (``mosiv run``'s files), ``close_loop/`` (the loop's), ``log.txt``
and, once the recording is finished, ``summary.json``. Resumable: a recording whose
``summary.json`` exists is skipped (remove its folder to run it again); a failed one writes its
error to ``error.txt`` and the others go on (the next batch tries it again); Ctrl-C cancels the
running tasks and writes the suite report of what is finished, which each task has already
written whole (``io.files``). ``progress`` hears, whenever it changes, how many recordings are
done, running, failed and waiting, with an estimate of the time left.

The suite report in ``out`` (``batch.json``, ``batch.md``, ``batch.png``): per recording and per
material pair (the families of its objects, in id order: the truth's for a synthetic
recording) CD and EMD on the observed and the future frames, the CD against the ground truth and
the parameter errors where there is one, the loop's verdicts (judged against the truth by
``loop.truth``) and the times.

What it is for: the command and benchmarks over many recordings. What it is not for: one
recording (``pipeline``, ``loop.report``). Ray is imported only inside the functions that need it.
"""

from __future__ import annotations

import json
import logging
import math
import time
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from mosiv_ros.config import BatchConfig
from mosiv_ros.identify.run import build_kernels_aside
from mosiv_ros.io.bag import find_bags
from mosiv_ros.io.files import OutputDir, plain, write_text
from mosiv_ros.loop.closure import LoopConfig
from mosiv_ros.loop.report import close_loop_prepared, mm
from mosiv_ros.loop.truth import judge
from mosiv_ros.pipeline import run_prepared
from mosiv_ros.prepare import RunConfig, prepare
from mosiv_ros.progress import TimeLeft, duration
from mosiv_ros.synth.ground_truth import read_ground_truth

_LOG = logging.getLogger(__name__)

SUMMARY = "summary.json"
"""A recording's batch report; its presence means the recording is finished."""
ERROR = "error.txt"
"""A failed recording's error and traceback."""
LOG_FILE = "log.txt"
"""A recording's log (the stages' logging, as ``mosiv run`` prints it)."""
RUN_DIR = "run"
"""The folder of a recording's ``mosiv run`` files."""
LOOP_DIR = "close_loop"
"""The folder of a recording's ``mosiv close-loop`` files."""
POLL_S = 1.0
"""Seconds between looks at the running tasks (Ctrl-C is heard at once regardless)."""
PARTS = ("observed", "future")
SCORES = ("cd", "emd", "cd_truth")


@dataclass(frozen=True)
class Item:
    """One recording of a batch: its folder's name in ``out`` and its bag directory."""

    name: str
    bag: Path


@dataclass(frozen=True)
class BatchStatus:
    """Where a batch stands: recordings done, running, failed and waiting; the time left."""

    total: int
    skipped: int
    done: int
    running: int
    failed: int
    waiting: int
    seconds_left: float | None

    def line(self) -> str:
        return (f"{self.done}/{self.total} done ({self.skipped} from before), {self.running} running, "
                f"{self.failed} failed, {self.waiting} waiting; time left {duration(self.seconds_left)}")


def find_items(paths: Iterable[str | Path]) -> list[Item]:
    """The recordings under ``paths`` with their folder names; ValueError if two names collide."""
    items: dict[str, Item] = {}
    for root in map(Path, paths):
        for bag in find_bags([root]):
            name = "__".join(bag.relative_to(root).parts) or root.resolve().name
            if name in items and items[name].bag.resolve() != bag.resolve():
                raise ValueError(f"{items[name].bag} and {bag} would share the folder {name!r}: "
                                 "give their parent directory instead")
            items.setdefault(name, Item(name, bag))
    return list(items.values())


def task_resources(config: RunConfig, cluster: dict[str, float], per_gpu: int = 1) -> tuple[dict[str, float], str]:
    """The Ray resources of one recording's task and the device it simulates on.

    On CUDA a task asks for ``1 / per_gpu`` of a GPU (``BatchConfig.per_gpu``).
    """
    device = config.identify.device
    if device == "auto":
        device = "cuda" if cluster.get("GPU", 0) >= 1 else "cpu"
    if device.startswith("cuda"):
        if cluster.get("GPU", 0) < 1:
            raise ValueError(f"device {config.identify.device!r}: the Ray cluster has no GPU")
        return {"num_gpus": 1 / per_gpu, "num_cpus": 1}, "cuda:0"  # Ray makes the task's GPU cuda:0
    cores = config.identify.cpu_workers or 1
    if cluster.get("CPU", 0) < cores:
        raise ValueError(f"cpu_workers {cores}: the Ray cluster has only {cluster.get('CPU', 0):g} CPU cores")
    return {"num_cpus": cores}, "cpu"


def _slots(resources: dict[str, float], cluster: dict[str, float]) -> int:
    """How many tasks of ``resources`` the cluster runs at once (at least 1)."""
    key = "GPU" if resources.get("num_gpus") else "CPU"
    need = resources.get("num_gpus") or resources["num_cpus"]
    return max(1, int(cluster.get(key, 0) / need + 1e-9))  # 1 / (1/3) is 3, not 2.999...


def process(item: Item, folder: Path, config: RunConfig, loop: LoopConfig | None, device: str) -> dict:
    """One recording's task: run it (and close its loop), write ``summary.json`` or ``error.txt``."""
    folder.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(folder / LOG_FILE, mode="w", encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logger = logging.getLogger("mosiv_ros")
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    identify = replace(config.identify, device=device)
    if device == "cpu":
        identify.cpu_workers = identify.cpu_workers or 1
    config = replace(config, identify=identify, prediction=replace(config.prediction, device=device))
    # every fit checkpoints in the recording's own folders: a stopped batch resumes it mid-fit
    checkpoints = Path(identify.checkpoint_dir) / item.name if identify.checkpoint_dir else folder
    start = time.perf_counter()
    try:
        run_out = OutputDir(folder / RUN_DIR, f"mosiv batch: mosiv run {item.bag}")
        build_kernels_aside(device)  # while the recording is reconstructed
        prepared = prepare(item.bag, config)
        report = run_prepared(prepared, run_out, _checkpointed(config, checkpoints / RUN_DIR)).report
        seconds = {"run": time.perf_counter() - start}
        loop_report = None
        if loop is not None:
            tick = time.perf_counter()
            loop_out = OutputDir(folder / LOOP_DIR, f"mosiv batch: mosiv close-loop {item.bag}")
            loop_report = close_loop_prepared(prepared, loop_out, _checkpointed(config, checkpoints / LOOP_DIR),
                                              loop)
            seconds["close_loop"] = time.perf_counter() - tick
        truth = read_ground_truth(item.bag) if (item.bag / "ground_truth.yaml").is_file() else None
        entry = summarise(item, report, loop_report, truth)
    except Exception as error:  # a recording that fails keeps its error; the others go on
        _LOG.exception("%s failed", item.bag)
        return failed(item, folder, f"{type(error).__name__}: {error}", traceback.format_exc(),
                      time.perf_counter() - start)
    finally:
        logger.removeHandler(handler)
        handler.close()
    entry["seconds"] = {**seconds, "total": time.perf_counter() - start}
    write_text(folder / SUMMARY, json.dumps(plain(entry, null_nonfinite=True), indent=1))
    (folder / ERROR).unlink(missing_ok=True)
    return entry


def _checkpointed(config: RunConfig, folder: Path) -> RunConfig:
    """``config`` with its fits checkpointing under ``folder/checkpoints``."""
    return replace(config, identify=replace(config.identify, checkpoint_dir=str(folder / "checkpoints")))


def failed(item: Item, folder: Path, error: str, trace: str, seconds: float) -> dict:
    """A failed recording's entry; its error and traceback go to ``folder/error.txt``."""
    folder.mkdir(parents=True, exist_ok=True)
    write_text(folder / ERROR, f"{error}\n\n{trace}")
    return {"recording": item.name, "bag": str(item.bag), "status": "failed", "error": error,
            "seconds": {"total": seconds}}


def summarise(item: Item, report: dict, loop_report: dict | None, truth: dict | None) -> dict:
    """A finished recording's entry in the suite report, from its run (and loop) report."""
    objects = report["estimates"]["objects"]
    families = ([o["family"] for o in truth["objects"]] if truth is not None
                else [o["family"] for o in objects])
    metrics = report["metrics"]
    entry = {
        "recording": item.name, "bag": str(item.bag), "status": "done",
        "objects": [o["name"] for o in objects], "families": families, "pair": " / ".join(families),
        "frames": report["frames"], "fitted_frames": report["fitted_frames"],
        "scores": {part: {key: metrics[part][key] for key in SCORES if key in metrics[part]}
                   for part in PARTS if part in metrics},
    }
    if report.get("views"):
        entry["views"] = {name: {"cut": len(v["cut"]), "missing": len(v["missing"])}
                          for name, v in report["views"].items()}
    if "parameter_errors" in report:
        entry["parameter_errors"] = report["parameter_errors"]
        entry["scale_error_dex"] = scale_error(report["parameter_errors"])
    if loop_report is not None:
        entry["loop"] = judge(loop_report, truth)
    return entry


def scale_error(errors: dict[str, dict[str, dict]]) -> float | None:
    """Mean |log10 ratio| of every scale parameter (E, yield stress, ...) against the truth."""
    values = [abs(e["log10_ratio"]) for params in errors.values() for e in params.values()
              if "log10_ratio" in e and e["log10_ratio"] is not None and math.isfinite(e["log10_ratio"])]
    return float(np.mean(values)) if values else None


def aggregate(entries: list[dict]) -> dict[str, dict]:
    """Per material pair, and over all (``"all"``), the mean of each score over finished recordings."""
    done = [e for e in entries if e["status"] == "done"]
    groups: dict[str, list[dict]] = {}
    for entry in done:
        groups.setdefault(entry["pair"], []).append(entry)
    if done:
        groups["all"] = done
    table = {}
    for pair, members in sorted(groups.items(), key=lambda kv: (kv[0] == "all", kv[0])):
        row: dict = {"recordings": len(members)}
        for part in PARTS:
            for key in SCORES:
                values = [m["scores"][part][key] for m in members
                          if key in m["scores"].get(part, {}) and m["scores"][part][key] is not None]
                row[f"{key}_{part}"] = float(np.mean(values)) if values else None
        dex = [m["scale_error_dex"] for m in members if m.get("scale_error_dex") is not None]
        row["scale_error_dex"] = float(np.mean(dex)) if dex else None
        outcomes = [m["loop"]["outcome"] for m in members if "outcome" in m.get("loop", {})]
        if outcomes:
            row["loop_outcomes"] = {o: outcomes.count(o) for o in sorted(set(outcomes))}
        table[pair] = row
    return table


def run_batch(paths: Iterable[str | Path], out: str | Path, config: RunConfig,
              batch: BatchConfig | None = None, loop: LoopConfig | None = None,
              progress: Callable[[BatchStatus], None] | None = None) -> dict:
    """Run every recording under ``paths`` (the module docstring); return the suite report.

    ``loop`` (the loop's settings) is used when ``batch.close_loop`` is on. The report's
    ``interrupted`` is True when Ctrl-C stopped the batch.
    """
    import ray

    batch = batch or BatchConfig()
    items = find_items(paths)
    directory = OutputDir(out, f"mosiv batch {' '.join(map(str, paths))}")  # before any work
    loop = (loop or LoopConfig(holdout=config.holdout)) if batch.close_loop else None
    entries: dict[str, dict] = {}
    _add_written(directory, items, entries)
    skipped = len(entries)
    waiting = [item for item in items if item.name not in entries]
    started = not ray.is_initialized() and not batch.address
    if batch.address:
        ray.init(address=batch.address, log_to_driver=False)
    elif started:
        ray.init(num_cpus=batch.cpus or None, include_dashboard=False, log_to_driver=False)
    interrupted = False
    try:
        resources, device = task_resources(config, ray.cluster_resources(), batch.per_gpu)
        task = ray.remote(process).options(**resources, max_retries=0)
        running: dict = {}
        clock = TimeLeft()
        todo = len(waiting)

        def tell() -> None:
            finished = len(entries) - skipped
            if progress is not None:
                progress(BatchStatus(len(items), skipped, len(entries) - failures(entries), len(running),
                                     failures(entries), len(waiting), clock("batch", finished, todo)))

        clock("batch", 0, todo)  # the estimate's start
        while waiting or running:
            slots = _slots(resources, ray.cluster_resources())
            submitted = min(len(waiting), max(0, slots - len(running)))
            for item in waiting[:submitted]:
                running[task.remote(item, directory.path / item.name, config, loop, device)] = item
            del waiting[:submitted]
            if submitted:
                tell()
            ready, _ = ray.wait(list(running), num_returns=1, timeout=POLL_S)
            for ref in ready:
                item = running.pop(ref)
                try:
                    entries[item.name] = ray.get(ref)
                except Exception as error:  # the worker died (killed, out of memory) or Ray failed
                    entries[item.name] = failed(item, directory.path / item.name, f"{type(error).__name__}: "
                                                f"{error}", traceback.format_exc(), 0.0)
            if ready:
                tell()
    except KeyboardInterrupt:
        interrupted = True
        for ref in running:
            ray.cancel(ref, force=True)
        # a recording that wrote its summary as Ctrl-C came is done, though its result never arrived
        _add_written(directory, items, entries)
        _LOG.warning("interrupted: %d running recordings cancelled; the finished ones are kept",
                     sum(item.name not in entries for item in running.values()))
    finally:
        if started:
            ray.shutdown()
    ordered = [entries[item.name] for item in items if item.name in entries]
    return write_suite_report(directory, ordered, len(items), interrupted)


def _add_written(directory: OutputDir, items: list[Item], entries: dict[str, dict]) -> None:
    """Add to ``entries`` each recording of ``items`` not in it whose ``summary.json`` is written."""
    for item in items:
        summary = directory.path / item.name / SUMMARY
        if item.name not in entries and summary.is_file():
            entries[item.name] = json.loads(summary.read_text(encoding="utf-8"))


def failures(entries: dict[str, dict]) -> int:
    return sum(entry["status"] == "failed" for entry in entries.values())


def write_suite_report(out: OutputDir, entries: list[dict], total: int, interrupted: bool) -> dict:
    """Write ``batch.json``, ``batch.md`` and ``batch.png`` into ``out``; return the report."""
    report = {"recordings": total, "done": sum(e["status"] == "done" for e in entries),
              "failed": sum(e["status"] == "failed" for e in entries), "interrupted": interrupted,
              "per_pair": aggregate(entries), "per_recording": entries}
    out.write_text("batch.json", json.dumps(plain(report, null_nonfinite=True), indent=1))
    plot = _plot(out, report["per_pair"])
    out.write_text("batch.md", markdown(report, plot))
    return report


def markdown(report: dict, plot: str | None) -> str:
    """The suite report for a person to read."""
    lines = [f"# mosiv batch: {report['recordings']} recordings", "",
             f"{report['done']} done, {report['failed']} failed"
             + (", interrupted (Ctrl-C) before the rest" if report["interrupted"] else "") + ". "
             "CD and EMD (mm) of the twin against the reconstruction, CD vs truth against the "
             "ground-truth particles; observed = the fitted frames, future = the held-out ones.",
             "", "## Per material pair", "",
             "| pair | recordings | CD observed | CD future | EMD observed | EMD future | CD vs truth observed "
             "| CD vs truth future | scale params mean abs log10 error | loop outcomes |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for pair, row in report["per_pair"].items():
        dex = "" if row["scale_error_dex"] is None else f"{row['scale_error_dex']:.2f}"
        outcomes = ", ".join(f"{k} {v}" for k, v in row.get("loop_outcomes", {}).items())
        lines.append(f"| {pair} | {row['recordings']} | " + " | ".join(
            mm(row[f"{key}_{part}"]) for key in ("cd", "emd", "cd_truth") for part in PARTS)
            + f" | {dex} | {outcomes} |")
    lines += ["", "## Per recording", "",
              "| recording | pair | CD observed | CD future | EMD observed | EMD future | scale params log10 "
              "error | loop: verdict, named (outcome), held-out mm before -> after | time (s) |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for entry in report["per_recording"]:
        seconds = f"{entry['seconds']['total']:.0f}"
        if entry["status"] == "failed":
            lines.append(f"| {entry['recording']} | | failed: {entry['error'][:120]} | | | | | | {seconds} |")
            continue
        scores = entry["scores"]
        cells = [mm(scores.get(part, {}).get(key)) for key in ("cd", "emd") for part in PARTS]
        dex = "" if entry.get("scale_error_dex") is None else f"{entry['scale_error_dex']:.2f}"
        loop = entry.get("loop")
        verdict = "" if loop is None else (
            f"{loop['verdict']}, {', '.join(loop['named']) or 'nothing'}"
            + (f" ({loop['outcome']})" if "outcome" in loop else "")
            + f", {mm(loop['held_out_before'])} -> {mm(loop['held_out_after'])}")
        lines.append(f"| {entry['recording']} | {entry['pair']} | " + " | ".join(cells)
                     + f" | {dex} | {verdict} | {seconds} |")
    partial = [(entry["recording"], name, v) for entry in report["per_recording"]
               for name, v in entry.get("views", {}).items()]
    if partial:
        lines += ["", "Objects the views do not show whole (their scores cover only what the cameras show): "
                  + "; ".join(f"{recording}: {name} cut by an image border in {_frames(v['cut'])}, no geometry "
                              f"in {_frames(v['missing'])}" for recording, name, v in partial) + "."]
    if plot:
        lines += ["", f"![{plot}]({plot})"]
    return "\n".join(lines) + "\n"


def _frames(count: int) -> str:
    return f"{count} frame" if count == 1 else f"{count} frames"


def _plot(out: OutputDir, per_pair: dict[str, dict]) -> str | None:
    """CD and EMD per material pair, observed beside future: ``batch.png``."""
    if not per_pair:
        return None
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    pairs = list(per_pair)
    x = np.arange(len(pairs))
    figure, axes = plt.subplots(1, 2, figsize=(max(8.0, 1.2 * len(pairs)), 4.0))
    for axis, key, label in ((axes[0], "cd", "CD (mm)"), (axes[1], "emd", "EMD (mm)")):
        for offset, part in ((-0.2, "observed"), (0.2, "future")):
            values = [np.nan if per_pair[p][f"{key}_{part}"] is None else per_pair[p][f"{key}_{part}"] * 1e3
                      for p in pairs]
            axis.bar(x + offset, values, width=0.4, label=part)
        axis.set_xticks(x, pairs, rotation=45, ha="right", fontsize=7)
        axis.set(ylabel=label, title=f"{label[:-5]} per material pair")
        axis.legend(fontsize=7)
    figure.tight_layout()
    out.save_figure("batch.png", figure)
    plt.close(figure)
    return "batch.png"
