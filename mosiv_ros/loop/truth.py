"""The loop closure's answer judged against a synthetic recording's ground truth.

The truth's undeclared effects are what the loop should name: a library effect by its name (a
tilted gravity by ``wind``, which stands for it), an effect outside the library
(``periodic_field``) by nothing, and mask noise is not an effect to name. ``judge`` sums a
``close_loop`` report up against the truth: the verdict, what was named with each fitted
value's error against the truth, the held-out centroid error before and after (and that of the
first round's control and of the reconstruction itself, the floor), and the
outcome: 'right', 'missed' (a present effect not named) or 'wrong name' (one named that is not
there, the worst).

What it is for: the batch report (``mosiv_ros.batch``) and ``benchmarks/loop_suite.py``.
What it is not for: running the loop (``loop.report.close_loop``).
"""

from __future__ import annotations

STANDS_FOR = {"gravity": "wind"}
"""Truth effect types the library names otherwise."""
NOT_NAMED = {"mask_noise"}
"""Truth effect types that are noise, not an effect to name."""
OUTSIDE = {"periodic_field"}
"""Truth effect types outside the library: the right answer is no name."""


def expected(truth: dict) -> list[str]:
    """The library names the loop should give: one per undeclared effect it can name."""
    names = []
    for effect in truth.get("effects", []):
        kind = effect.get("type")
        if effect.get("declared") or kind in NOT_NAMED or kind in OUTSIDE:
            continue
        names.append(STANDS_FOR.get(kind, kind))
    return sorted(set(names))


def value_errors(name: str, values: dict[str, float], truth: dict) -> dict[str, float]:
    """Each fitted knob of an accepted effect against the truth (relative, or absolute in SI)."""
    effects = {STANDS_FOR.get(e["type"], e["type"]): e for e in truth.get("effects", [])
               if not e.get("declared")}
    effect = effects.get(name)
    if effect is None:
        return {}
    params = effect.get("params", {})
    errors = {}
    for label, value in values.items():
        inside = label[label.index("[") + 1: -1] if "[" in label else ""
        if name in ("drag", "linear_drag", "damping"):
            true = next(iter(params.values()), {}).get(inside)
            if true:
                errors[label] = (value - true) / true
        elif name == "wind":
            vector = params.get("a") or params.get("g")
            if vector is not None:
                errors[label] = value - float(vector[int(inside)])
        elif name == "floor_tilt":
            normal = params.get("normal")
            if normal:
                errors[label] = value - float(normal[int(inside)]) / float(normal[2])
        elif name == "floor_friction":
            errors[label] = (value - float(params["friction"])) / float(params["friction"])
        elif name == "camera_time_offset" and params.get("camera") == inside:
            errors[label] = value - float(params["offset"])
    return errors


def outcome(named: list[str], should_name: list[str]) -> str:
    """'right', 'missed' (a present effect not named), 'wrong name' (one named that is not there)."""
    if set(named) - set(should_name):
        return "wrong name"
    return "right" if set(named) == set(should_name) else "missed"


def judge(report: dict, truth: dict | None) -> dict:
    """A ``close_loop`` report summed up, and with a ``truth`` judged against it."""
    named = [effect["name"] for effect in report["accepted"]]
    entry = {
        "verdict": report["verdict"], "named": named,
        "values": {e["name"]: e["values"] for e in report["accepted"]},
        "held_out_before": report["before"]["centroid_error"]["held_out"],
        "held_out_after": report["after"]["centroid_error"]["held_out"],
        "held_out_control": next((r["control"]["centroid_error"]["held_out"] for r in report["rounds"]
                                  if r.get("control")), None),
        "held_out_floor": (report.get("reconstruction_floor") or {}).get("held_out"),
        "free_flight": report.get("free_flight"),
    }
    if truth is not None:
        entry["expected"] = expected(truth)
        entry["value_errors"] = {e["name"]: value_errors(e["name"], e["values"], truth)
                                 for e in report["accepted"]}
        entry["outcome"] = outcome(named, entry["expected"])
    return entry
