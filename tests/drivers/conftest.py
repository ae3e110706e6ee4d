"""Driver tests: fail any test that leaves a thread running (pymodbus's idea), and turn on pylon's
camera emulation for this test session.

The leak check snapshots the live threads when a test starts (after the session- and module-scoped
fixtures it uses are up, since autouse function fixtures come after them) and, when it ends (after
its other function fixtures were torn down), waits a short while for extra threads to finish.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator

import pytest

# Emulated Basler cameras for the whole session. pylon reads PYLON_CAMEMU when it enumerates
# devices (checked with pypylon 26.9: setting it in-process before the first EnumerateDevices()
# is enough), so setting it here, before any test opens a camera, works without a subprocess.
PYLON_EMULATED_CAMERAS = 3


@pytest.fixture(scope="session", autouse=True)
def pylon_emulation() -> Iterator[int]:
    old = os.environ.get("PYLON_CAMEMU")
    os.environ["PYLON_CAMEMU"] = str(PYLON_EMULATED_CAMERAS)
    yield PYLON_EMULATED_CAMERAS
    if old is None:
        os.environ.pop("PYLON_CAMEMU", None)
    else:
        os.environ["PYLON_CAMEMU"] = old


@pytest.fixture(autouse=True)
def no_thread_leak() -> Iterator[None]:
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 3.0
    while True:
        extra = [t for t in threading.enumerate() if t not in before and t.is_alive()]
        if not extra or time.monotonic() > deadline:
            break
        extra[0].join(timeout=0.05)  # wait for the condition (threads ending), not a fixed time
    if extra:
        pytest.fail(f"test leaked {len(extra)} thread(s): {[t.name for t in extra]}")
