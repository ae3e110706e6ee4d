"""The layer rule: mvpose_core imports neither drivers nor server; drivers never import server;
the station process (server/station) imports nothing of the API (server.api) or the page
(server.web)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"mvpose_core": {"drivers", "server"}, "drivers": {"server"}}


def imported_modules(path: Path) -> set[str]:
    """Every absolute module name ``path`` imports, wherever the import stands."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            out.add(node.args[0].value)
    return out


def imported_packages(path: Path) -> set[str]:
    return {name.split(".")[0] for name in imported_modules(path)}


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
        "import server.app\nfrom drivers.links import x\nimportlib.import_module('server.cli')\n"
    )
    assert imported_packages(f) == {"server", "drivers"}
    f.write_text("from .sibling import y\nimport numpy as np\n")
    assert imported_packages(f) == {"numpy"}


STATION_FORBIDDEN = ("server.api", "server.web", "server.app")


def _forbidden_for_station(name: str) -> bool:
    return any(name == f or name.startswith(f + ".") for f in STATION_FORBIDDEN)


def test_the_station_process_imports_nothing_of_the_api_or_the_page() -> None:
    # directly, in any of its modules (an import inside a function included) ...
    station = sorted((ROOT / "server" / "station").glob("*.py"))
    assert station
    direct = [f"{path.relative_to(ROOT)} imports {name}" for path in station
              for name in sorted(imported_modules(path)) if _forbidden_for_station(name)]
    assert direct == []
    # ... and through what they import: every module of the package in a fresh interpreter
    names = ", ".join(f"server.station.{p.stem}" for p in station if p.stem != "__init__")
    code = (f"import sys, {names}\n"
            f"print(sorted(m for m in sys.modules if m.startswith({STATION_FORBIDDEN!r})))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_the_station_check_sees_an_api_import(tmp_path: Path) -> None:
    f = tmp_path / "x.py"
    f.write_text("def later():\n    from server.api.versions import check_calibration\n")
    assert [n for n in imported_modules(f) if _forbidden_for_station(n)] == [
        "server.api.versions"]
    assert not _forbidden_for_station("server.apis") and _forbidden_for_station("server.web")
