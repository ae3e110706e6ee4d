"""Waiting for a condition in an async test: poll it with a deadline, fail naming what did not
happen."""

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
