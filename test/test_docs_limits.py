"""docs/limits.md's table of parameter ranges is the one config.py holds: every ranged parameter
of every node, with its default and range, and nothing else."""

from __future__ import annotations

import re
from pathlib import Path

from mosiv_ros.config import STAGE_CONFIGS, parameters, value_of

LIMITS = Path(__file__).resolve().parents[1] / "docs" / "limits.md"


def _table() -> dict[tuple[str, str], tuple[str, float, float]]:
    rows, node = {}, ""
    text = LIMITS.read_text().split("### Parameter ranges", 1)[1].split("\n### ", 1)[0]
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 5 or not cells[1].startswith("`"):
            continue
        node = cells[0] or node
        name = re.match(r"`([\w.]+)`", cells[1]).group(1)
        rows[(node, name)] = (cells[2], float(cells[3]), float(cells[4]))
    return rows


def test_the_parameter_table_of_docs_limits_is_the_configs():
    expected = {}
    for node, config_type in STAGE_CONFIGS.items():
        defaults = config_type()
        for name, f, _ in parameters(config_type):  # a group's by dotted name: search.samples
            if f.metadata.get("range") is not None:
                expected[(node, name)] = (value_of(defaults, name), *f.metadata["range"])
    table = _table()
    assert set(table) == set(expected)
    for key, (default, low, high) in expected.items():
        shown, shown_low, shown_high = table[key]
        assert (shown_low, shown_high) == (low, high), key
        assert shown == str(default) or float(shown) == default, key
