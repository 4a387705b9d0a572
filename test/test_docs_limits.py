"""docs/limits.md's table of parameter ranges is the one config.py holds: every ranged parameter
of every node, with its default and range, and nothing else."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

from mosiv_ros.config import STAGE_CONFIGS

LIMITS = Path(__file__).resolve().parents[1] / "docs" / "limits.md"


def _table() -> dict[tuple[str, str], tuple[str, float, float]]:
    rows, node = {}, ""
    text = LIMITS.read_text().split("### Parameter ranges", 1)[1].split("\n### ", 1)[0]
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 5 or not cells[1].startswith("`"):
            continue
        node = cells[0] or node
        name = re.match(r"`(\w+)`", cells[1]).group(1)
        rows[(node, name)] = (cells[2], float(cells[3]), float(cells[4]))
    return rows


def test_the_parameter_table_of_docs_limits_is_the_configs():
    expected = {}
    for node, config_type in STAGE_CONFIGS.items():
        defaults = config_type()
        for f in dataclasses.fields(config_type):
            if f.metadata.get("range") is not None:
                expected[(node, f.name)] = (getattr(defaults, f.name), *f.metadata["range"])
    table = _table()
    assert set(table) == set(expected)
    for key, (default, low, high) in expected.items():
        shown, shown_low, shown_high = table[key]
        assert (shown_low, shown_high) == (low, high), key
        assert shown == str(default) or float(shown) == default, key
