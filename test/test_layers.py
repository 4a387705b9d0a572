"""The core's layers: a module never imports one that builds on it (imports inside functions too)."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mosiv_ros"

# (modules under this path, modules they must not import): each a layer above its importer
FORBIDDEN = [
    ("predict", ("mosiv_ros.identify.fit", "mosiv_ros.identify.problem")),
    ("identify", ("mosiv_ros.evaluate", "mosiv_ros.loop", "mosiv_ros.pipeline", "mosiv_ros.report")),
    ("loop", ("mosiv_ros.pipeline", "mosiv_ros.report")),
    ("prepare.py", ("mosiv_ros.identify", "mosiv_ros.loop", "mosiv_ros.pipeline", "mosiv_ros.report")),
    ("io/scene.py", ("mosiv_ros.io.bag",)),
    ("simulation.py", ("mosiv_ros.identify", "mosiv_ros.predict")),
    ("metrics.py", ("mosiv_ros",)),
]


def imported(path: Path) -> set[str]:
    """Every module a file imports, at any depth of its code."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


@pytest.mark.parametrize(("where", "above"), FORBIDDEN, ids=[where for where, _ in FORBIDDEN])
def test_a_layer_imports_nothing_that_builds_on_it(where, above):
    root = PACKAGE / where
    files = sorted(root.rglob("*.py")) if root.is_dir() else [root]
    assert files
    offenders = [f"{path.relative_to(PACKAGE)}: {name}" for path in files for name in imported(path)
                 if any(name == a or name.startswith(a + ".") for a in above)]
    assert not offenders
