"""node-opcua's client as the OPC UA tests' second client stack, beside asyncua.

A defect that asyncua's server and asyncua's client share (both read the same filters, the same
types, the same policies) hides from a test that uses asyncua on both ends; node-opcua is another
implementation. ``tests/peers/node-opcua`` pins it (package.json, package-lock.json); `make venv`
installs it with ``npm ci``, and :func:`run` does so when it is missing (a clean clone). The
client's steps are in ``peer.mjs`` (see its header); :func:`run` hands it one JSON spec and returns
the JSON it prints.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import threading
from pathlib import Path
from typing import Any

from system_packages import ensure_commands

PEER_DIR = Path(__file__).resolve().parent / "peers" / "node-opcua"
_lock = threading.Lock()


def install() -> str:
    """The ``node`` command, with the pinned node-opcua client installed (``npm ci``)."""
    commands = ensure_commands({"node": "nodejs", "npm": "npm"})
    with _lock:
        lock = PEER_DIR / "package-lock.json"
        done = PEER_DIR / "node_modules" / ".package-lock.json"  # npm writes it last
        if not done.is_file() or done.stat().st_mtime < lock.stat().st_mtime:
            subprocess.run([commands["npm"], "ci", "--prefix", str(PEER_DIR), "--ignore-scripts",
                            "--no-audit", "--no-fund", "--loglevel=error"],
                           check=True, timeout=900)
    return commands["node"]


async def run(spec: dict[str, Any], timeout_s: float = 180.0) -> dict[str, Any]:
    """Run ``peer.mjs`` with ``spec``; its JSON answer (``connected``, ``results``, ``error``)."""
    node = install()
    proc = await asyncio.create_subprocess_exec(
        node, str(PEER_DIR / "peer.mjs"), json.dumps(spec), cwd=str(PEER_DIR),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    try:
        out, err = await asyncio.wait_for(proc.communicate(), timeout_s)
    except TimeoutError:
        proc.kill()
        await proc.wait()
        raise
    lines = [ln for ln in out.decode().splitlines() if ln.startswith("{")]
    assert proc.returncode == 0 and lines, (
        f"node-opcua peer failed (rc {proc.returncode}): {err.decode()[-3000:]}")
    answer: dict[str, Any] = json.loads(lines[-1])
    return answer
