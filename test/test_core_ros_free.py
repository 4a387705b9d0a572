"""The core never imports rclpy: only mosiv_ros/nodes/ does."""

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mosiv_ros"


def core_modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        if "nodes" not in path.relative_to(PACKAGE).parts:
            yield path


def test_no_core_module_imports_rclpy():
    offenders = []
    for path in core_modules():
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            offenders += [f"{path}: {n}" for n in names if n.split(".")[0] == "rclpy"]
    assert not offenders


def test_importing_every_core_module_loads_no_rclpy():
    modules = [
        ".".join(p.relative_to(PACKAGE.parent).with_suffix("").parts)
        for p in core_modules()
        if p.name not in ("__main__.py",)
    ]
    code = (
        "import importlib, sys\n"
        f"for m in {modules!r}: importlib.import_module(m)\n"
        "assert 'rclpy' not in sys.modules, 'rclpy was imported'\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
