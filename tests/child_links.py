"""A link in a process of its own (drivers.links.process), started for a test with the tests'
recording handler as the station, and stopped after it."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from opcua_handler import RecordingHandler
from waiting import until

from drivers.links import open_links
from drivers.links.process import ProcessLink


@asynccontextmanager
async def hosted_link(configs: dict[str, Any],
                      start_s: float) -> AsyncIterator[tuple[ProcessLink, RecordingHandler]]:
    """The one link of ``configs`` in its child process, once its server listens (within
    ``start_s``), with the handler that records what it was asked."""
    handler = RecordingHandler()
    (link,) = open_links(configs, handler)
    assert isinstance(link, ProcessLink) and link.name in configs
    await link.start()
    try:
        await until(link.started.is_set, "the child's server listens", start_s)
        yield link, handler
    finally:
        await link.stop()
