"""axe-core in the browser tests: every page of the operator page checked for accessibility.

axe-core comes from npm, pinned by tests/peers/axe-core/package-lock.json and installed there by
``npm ci`` the first time a test needs it (``make venv`` installs it too). It is injected into
the page under test (Playwright's ``add_script_tag``), never served by the app.
"""

from __future__ import annotations

import subprocess
import threading
from pathlib import Path
from typing import Any

from system_packages import ensure_commands

PEER = Path(__file__).resolve().parents[1] / "peers" / "axe-core"
SCRIPT = PEER / "node_modules" / "axe-core" / "axe.min.js"
#: the impacts a page must not have
REFUSED = ("serious", "critical")
_lock = threading.Lock()


def axe_script() -> Path:
    """axe.min.js, installed by ``npm ci`` from the lock file when missing."""
    with _lock:
        if not SCRIPT.exists():
            npm = ensure_commands({"npm": "npm"})["npm"]
            subprocess.run([npm, "ci", "--prefix", str(PEER), "--ignore-scripts", "--no-audit",
                            "--no-fund", "--loglevel=error"], check=True, timeout=600)
        return SCRIPT


def violations(page: Any) -> list[dict[str, Any]]:
    """axe-core's serious and critical violations of the page as it is now."""
    if not page.evaluate("() => typeof window.axe === 'object'"):
        page.add_script_tag(path=str(axe_script()))
    found: list[dict[str, Any]] = page.evaluate("""async () => {
        const r = await axe.run(document, {resultTypes: ["violations"]});
        return r.violations.map((v) => ({id: v.id, impact: v.impact, help: v.help,
            nodes: v.nodes.slice(0, 4).map((n) => n.target.join(" ") + " — " + n.failureSummary)}));
    }""")
    return [v for v in found if v["impact"] in REFUSED]


def assert_accessible(page: Any, what: str) -> None:
    bad = violations(page)
    assert not bad, f"{what}: axe-core finds " + "; ".join(
        f"{v['impact']} {v['id']} ({v['help']}): {' | '.join(v['nodes'])}" for v in bad)
