"""The layer rule: mvpose_core imports neither drivers nor server; drivers never import server."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"mvpose_core": {"drivers", "server"}, "drivers": {"server"}}


def imported_packages(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            out.add(node.args[0].value.split(".")[0])
    return out


def violations(package: str) -> list[str]:
    bad = []
    for path in sorted((ROOT / package).rglob("*.py")):
        hits = imported_packages(path) & FORBIDDEN[package]
        if hits:
            bad.append(f"{path.relative_to(ROOT)} imports {sorted(hits)}")
    return bad


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_layer_rule(package: str) -> None:
    assert (ROOT / package).is_dir()
    assert violations(package) == []


def test_checker_sees_violations(tmp_path: Path) -> None:
    f = tmp_path / "x.py"
    f.write_text(
        "import server.app\nfrom drivers.plc import x\nimportlib.import_module('server.cli')\n"
    )
    assert imported_packages(f) == {"server", "drivers"}
    f.write_text("from .sibling import y\nimport numpy as np\n")
    assert imported_packages(f) == {"numpy"}
