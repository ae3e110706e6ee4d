"""An asyncua subscription handler that queues the events it is given (the OPC UA tests)."""

from __future__ import annotations

import asyncio
from typing import Any


class Events:
    """Pass to ``client.create_subscription``; :meth:`next` waits for the next event."""

    def __init__(self, timeout_s: float = 15.0) -> None:
        self.queue: asyncio.Queue[Any] = asyncio.Queue()
        self.timeout_s = timeout_s

    def event_notification(self, event: Any) -> None:
        self.queue.put_nowait(event)

    async def next(self) -> Any:
        return await asyncio.wait_for(self.queue.get(), self.timeout_s)
