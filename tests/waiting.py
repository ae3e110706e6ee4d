"""Waiting for a condition in a test: poll it with a deadline, fail naming what did not happen
(``until`` in an async test, ``until_sync`` in a plain one)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any


async def until(check: Callable[[], Any], what: str = "the condition", timeout_s: float = 10.0,
                every_s: float = 0.01) -> None:
    """Until ``check()`` is true; an AssertionError naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not check():
        assert time.monotonic() < deadline, f"{what}: not within {timeout_s:g} s"
        await asyncio.sleep(every_s)


def until_sync(check: Callable[[], Any], what: str = "the condition", timeout_s: float = 10.0,
               every_s: float = 0.01) -> None:
    """:func:`until` for a test without an event loop (the server runs in another thread)."""
    deadline = time.monotonic() + timeout_s
    while not check():
        assert time.monotonic() < deadline, f"{what}: not within {timeout_s:g} s"
        time.sleep(every_s)
