"""Record and run suite scenes side by side on one machine's GPUs, without Ray.

    python benchmarks/suite_run.py OUT [--size full] [--scenes 0,5,10] [--per-gpu 8]
        [--record-at-once 6] [--deadline 540] [--params-file F] [--device cuda|cpu]

For a GPU machine without Ray (``mosiv batch`` is the command where Ray is installed). Each scene
of ``mosiv_ros.synth.suite.suite_scenes(size)`` (all, or the indices given) is recorded with
``mosiv record`` into ``OUT/bags/`` (at most ``--record-at-once`` at a time) and then run as the
task ``mosiv batch`` runs (``mosiv_ros.batch.process``: ``config/mosiv.yaml``'s values or
``--params-file``'s, on ``cuda:0``, no 2D scores), ``--per-gpu`` recordings at a time on each GPU
(``CUDA_VISIBLE_DEVICES``; with ``--device cpu``, that many at a time on the CPU, one core each).
Each writes ``OUT/<scene>/`` as ``mosiv batch`` does; a scene whose ``summary.json`` exists is
skipped, so a rerun resumes; a scene stopped part-way goes on from its fits' checkpoints (in its
folder). Whatever still runs ``--deadline`` seconds after the start is stopped. At the end the
suite report (``OUT/batch.md``, ``batch.json``, ``batch.png``) covers every finished scene in OUT.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import yaml

from mosiv_ros.batch import SUMMARY, write_suite_report
from mosiv_ros.io.files import OutputDir
from mosiv_ros.synth.suite import suite_scenes

TASK = """
import sys
from pathlib import Path
from mosiv_ros.batch import Item, process
from mosiv_ros.cli import run_config
from mosiv_ros.config import HOLDOUT
name, bag, out, params, device = sys.argv[1:6]
config = run_config(Path(params) if params else None, device, {}, holdout=HOLDOUT, render=False)
entry = process(Item(name, Path(bag)), Path(out) / name, config, None, device)
print(name, entry["status"], entry.get("error", ""), entry["seconds"])
"""


def gpu_count(device: str) -> int:
    if device == "cpu":
        return 1
    listed = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, check=True).stdout
    return max(1, sum(line.startswith("GPU ") for line in listed.splitlines()))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--size", default="full")
    parser.add_argument("--scenes", default="", help="comma-separated scene indices (default: all)")
    parser.add_argument("--per-gpu", type=int, default=8)
    parser.add_argument("--record-at-once", type=int, default=6)
    parser.add_argument("--deadline", type=float, default=float("inf"), help="seconds")
    parser.add_argument("--params-file", type=Path, default=None)
    parser.add_argument("--device", choices=("cuda", "cpu"), default="cuda")
    args = parser.parse_args()
    start = time.time()
    scenes = suite_scenes(args.size)
    picked = [scenes[int(i)] for i in args.scenes.split(",")] if args.scenes else scenes
    out = args.out.resolve()
    (out / "bags").mkdir(parents=True, exist_ok=True)
    (out / "scenes").mkdir(exist_ok=True)
    to_record = []
    for entry, document in picked:
        name = entry["name"]
        if not (out / name / SUMMARY).is_file():
            (out / "scenes" / f"{name}.yaml").write_text(yaml.safe_dump(document, sort_keys=False))
            to_record.append(name)
    gpus = gpu_count(args.device)
    device = "cuda:0" if args.device == "cuda" else "cpu"
    params = str(args.params_file.resolve()) if args.params_file else ""
    load = [0] * gpus
    recording: dict[str, tuple[subprocess.Popen, float]] = {}
    recorded: list[str] = []
    running: dict[str, tuple[subprocess.Popen, int, float]] = {}

    (out / "logs").mkdir(exist_ok=True)

    def launch(command: list[str], log: str, gpu: int) -> subprocess.Popen:
        """``command`` on GPU ``gpu``, its output to ``OUT/logs/<log>.log``."""
        with open(out / "logs" / f"{log}.log", "w") as file:  # the child keeps its own handle
            return subprocess.Popen(command, stdout=file, stderr=subprocess.STDOUT,
                                    env=dict(os.environ, CUDA_VISIBLE_DEVICES=str(gpu)))

    while to_record or recording or recorded or running:
        if time.time() - start > args.deadline:
            for name, (process, *_) in {**recording, **running}.items():
                process.kill()
                print(f"stopped {name} at the deadline", flush=True)
            break
        while to_record and len(recording) < args.record_at_once:
            name = to_record.pop(0)
            bag = out / "bags" / name
            if (bag / "metadata.yaml").is_file():
                recorded.append(name)
                continue
            command = [sys.executable, "-m", "mosiv_ros.cli", "record", str(out / "scenes" / f"{name}.yaml"), str(bag)]
            recording[name] = (launch(command, f"record_{name}", len(recording) % gpus), time.time())
        for name, (process, since) in list(recording.items()):
            if process.poll() is not None:
                del recording[name]
                print(f"recorded {name}: rc {process.returncode}, {time.time() - since:.0f} s", flush=True)
                if process.returncode == 0:
                    recorded.append(name)
        while recorded and min(load) < args.per_gpu:
            gpu = load.index(min(load))
            name = recorded.pop(0)
            command = [sys.executable, "-c", TASK, name, str(out / "bags" / name), str(out), params, device]
            running[name] = (launch(command, f"run_{name}", gpu), gpu, time.time())
            load[gpu] += 1
        for name, (process, gpu, since) in list(running.items()):
            if process.poll() is not None:
                del running[name]
                load[gpu] -= 1
                print(f"ran {name}: rc {process.returncode} on GPU {gpu}, {time.time() - since:.0f} s", flush=True)
        time.sleep(1.0)
    entries = [json.loads(path.read_text()) for path in sorted(out.glob(f"*/{SUMMARY}"))]
    write_suite_report(OutputDir(out, f"benchmarks/suite_run.py {out}"), entries, len(scenes), False)
    print(f"{len(entries)} of {len(scenes)} scenes finished in {out}; report: {out / 'batch.md'} "
          f"({time.time() - start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
