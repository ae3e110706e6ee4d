"""Debian packages the tests need (independent peers, brokers, a browser), installed when missing.

`make test` must pass on a clean machine: a test that needs mbpoll, Mosquitto or Chromium calls
:func:`ensure_commands` first. As root it runs ``apt-get update`` once per session and installs
what is missing; a machine where that cannot happen fails the test with the reason, never skips
it.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import threading

_lock = threading.Lock()
_updated = False


def ensure_commands(commands: dict[str, str]) -> dict[str, str]:
    """``{command: debian_package}`` → ``{command: absolute path}``, installing what is missing."""
    global _updated
    with _lock:
        missing = {cmd: pkg for cmd, pkg in commands.items() if _which(cmd) is None}
        if missing:
            if os.geteuid() != 0:
                raise RuntimeError(
                    f"commands {sorted(missing)} are missing and only root can install "
                    f"{sorted(set(missing.values()))} (apt-get install -y ...)")
            env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
            if not _updated:
                subprocess.run(["apt-get", "update", "-q"], check=True, env=env,
                               stdout=subprocess.DEVNULL, timeout=600)
                _updated = True
            subprocess.run(["apt-get", "install", "-y", "-q", "--no-install-recommends",
                            *sorted(set(missing.values()))], check=True, env=env,
                           stdout=subprocess.DEVNULL, timeout=900)
        found = {cmd: _which(cmd) for cmd in commands}
        absent = [cmd for cmd, path in found.items() if path is None]
        if absent:
            raise RuntimeError(f"commands {absent} still missing after apt-get install")
        return {cmd: str(path) for cmd, path in found.items()}


def _which(cmd: str) -> str | None:
    # Debian puts daemons like mosquitto in /usr/sbin, which a non-login PATH may lack.
    return shutil.which(cmd) or shutil.which(cmd, path="/usr/sbin:/usr/bin:/sbin:/bin")
