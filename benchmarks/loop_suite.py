"""The loop closure on many recordings: what it named against what the recordings hold.

    python benchmarks/loop_suite.py bags/thrown_ball bags/cube_on_slab /data/other_engine \\
        --params-file config/close_loop_cpu.yaml --out out/loop_suite

Every rosbag2 directory given, or found below a given directory, that carries a
``ground_truth.yaml`` goes through the loop closure (``mosiv close-loop``: ``loop.report``), its
report written to ``OUT/<recording>/``. The truth's undeclared effects are what should be
named (``mosiv_ros.loop.truth``). Writes ``OUT/loop_suite.json`` and ``OUT/loop_suite.md``: per
recording the truth, the verdict, what was named with each fitted value's error against the
truth, the held-out centroid error before and after, that of the first round's control (the
declared model refitted with a candidate's budget: how far refits of one model spread), the
reconstruction's own (the floor: the recorder's particles as the prediction), and the time; and
a confusion table of the true undeclared effect against what was named, in which a wrong name is
the worst cell. A recording whose loop fails keeps its error and the others go on.
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import sys
import time
import traceback
from collections import Counter
from pathlib import Path

from mosiv_ros.cli import add_loop_options, loop_options, run_config
from mosiv_ros.config import HOLDOUT
from mosiv_ros.io.bag import find_bags
from mosiv_ros.io.files import plain
from mosiv_ros.loop.closure import LoopConfig
from mosiv_ros.loop.report import close_loop, mm
from mosiv_ros.loop.truth import expected, judge
from mosiv_ros.synth.ground_truth import read_ground_truth


def recordings(paths: list[Path]) -> list[Path]:
    """Bag directories with a ground truth: the paths themselves, or found below them."""
    return [bag for bag in find_bags(paths) if (bag / "ground_truth.yaml").is_file()]


def one(bag: Path, out: Path, config, loop: LoopConfig) -> dict:
    truth = read_ground_truth(bag)
    entry = {"recording": bag.name, "path": str(bag), "expected": expected(truth),
             "truth_effects": truth.get("effects", [])}
    start = time.perf_counter()
    try:
        report = close_loop(bag, out / bag.name, config, loop)
    except Exception as error:  # a recording that fails keeps its error; the others go on
        entry.update({"error": f"{type(error).__name__}: {error}", "trace": traceback.format_exc(),
                      "seconds": time.perf_counter() - start})
        return entry
    entry.update(judge(report, truth))
    entry["seconds"] = time.perf_counter() - start
    return entry


def markdown(results: list[dict]) -> str:
    lines = ["# Loop closure suite", "",
             "| recording | undeclared (to name) | verdict | named | value errors | held-out before -> after (mm) "
             "| control (mm) | floor (mm) | outcome | time (s) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['recording']} | {', '.join(r['expected']) or 'none'} | error: {r['error'][:80]} "
                         f"| | | | | | | {r['seconds']:.0f} |")
            continue
        errors = "; ".join(f"{k} {v:+.3g}" for effect in r["value_errors"].values() for k, v in effect.items())
        lines.append(f"| {r['recording']} | {', '.join(r['expected']) or 'none'} | {r['verdict']} | "
                     f"{', '.join(r['named']) or 'nothing'} | {errors} | {mm(r['held_out_before'], 1)} -> "
                     f"{mm(r['held_out_after'], 1)} | {mm(r['held_out_control'], 1)} | {mm(r['held_out_floor'], 1)} | "
                     f"{r['outcome']} | {r['seconds']:.0f} |")
    counts = Counter((", ".join(r["expected"]) or "none", ", ".join(r["named"]) or "nothing")
                     for r in results if "error" not in r)
    columns = sorted({named for _, named in counts})
    lines += ["", "Confusion (rows: undeclared effects present; columns: what was named):", "",
              "| present | " + " | ".join(columns) + " |", "| --- |" + " --- |" * len(columns)]
    for row in sorted({present for present, _ in counts}):
        lines.append(f"| {row} | " + " | ".join(str(counts.get((row, c), "")) for c in columns) + " |")
    tally = Counter(r.get("outcome", "error") for r in results)
    lines += ["", ", ".join(f"{k}: {v}" for k, v in sorted(tally.items()))]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("paths", nargs="+", type=Path, help="bag directories or directories holding bags")
    parser.add_argument("--params-file", type=Path, default=None)
    parser.add_argument("--device", default=None)
    parser.add_argument("--holdout", type=float, default=HOLDOUT)
    add_loop_options(parser)
    parser.add_argument("--render", action="store_true", help="also score IoU, PSNR, SSIM")
    parser.add_argument("--out", type=Path, default=Path("out/loop_suite"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    bags = recordings(args.paths)
    if not bags:
        print("no recording with a ground_truth.yaml found", file=sys.stderr)
        return 2
    config = run_config(args.params_file, args.device, holdout=args.holdout, render=args.render)
    loop = LoopConfig(holdout=args.holdout, **loop_options(args))
    results = []
    for bag in bags:
        results.append(one(bag, args.out, config, loop))
        r = results[-1]
        print(f"{bag.name}: expected {r['expected'] or 'none'}, "
              + (f"error {r['error']}" if "error" in r else f"{r['verdict']}, named {r['named'] or 'nothing'}: "
                 f"{r['outcome']} ({r['seconds']:.0f} s)"), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {"benchmark": "loop_suite", "host": platform.node(), "python": sys.version.split()[0],
               "params_file": str(args.params_file), "device": args.device, "results": results,
               "wrong_names": sum(r.get("outcome") == "wrong name" for r in results),
               "right": sum(r.get("outcome") == "right" for r in results)}
    (args.out / "loop_suite.json").write_text(json.dumps(plain(summary, null_nonfinite=True), indent=1))
    (args.out / "loop_suite.md").write_text(markdown(results))
    print(markdown(results))
    print(f"wrote {args.out / 'loop_suite.json'} and {args.out / 'loop_suite.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
