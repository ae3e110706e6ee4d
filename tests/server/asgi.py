"""Run an ASGI app's lifespan in the test's event loop and talk to it through httpx ASGITransport.

This is what uvicorn does for the app in production (lifespan startup, state copied into every
request scope, shutdown), without a socket: the same middleware, auth and handlers run.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import httpx
from starlette.types import ASGIApp, Receive, Scope, Send


class StartupFailedError(RuntimeError):
    pass


@asynccontextmanager
async def running(
    app: ASGIApp, token: str | None = None
) -> AsyncIterator[tuple[httpx.AsyncClient, dict[str, Any]]]:
    """Start the app's lifespan; yield a client and the lifespan state; shut down on exit."""
    state: dict[str, Any] = {}
    to_app: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
    from_app: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
    scope = {"type": "lifespan", "asgi": {"version": "3.0", "spec_version": "2.0"}, "state": state}
    task = asyncio.create_task(app(scope, to_app.get, from_app.put))
    await to_app.put({"type": "lifespan.startup"})
    message = await _next(from_app, task)
    if message["type"] != "lifespan.startup.complete":
        try:
            await task
        except Exception as err:
            raise StartupFailedError(str(err)) from err
        raise StartupFailedError(message.get("message", "startup failed"))

    async def with_state(scope: Scope, receive: Receive, send: Send) -> None:
        await app({**scope, "state": dict(state)}, receive, send)

    headers = {"Authorization": f"Bearer {token}"} if token else {}
    transport = httpx.ASGITransport(app=with_state)
    try:
        async with httpx.AsyncClient(
            transport=transport, base_url="http://station", headers=headers
        ) as client:
            yield client, state
    finally:
        await to_app.put({"type": "lifespan.shutdown"})
        await _next(from_app, task)
        await task


async def _next(queue: asyncio.Queue[dict[str, Any]], task: asyncio.Task[Any]) -> dict[str, Any]:
    """The app's next lifespan message, or the app's exception if it stopped instead."""
    getter = asyncio.ensure_future(queue.get())
    done, _ = await asyncio.wait({getter, task}, return_when=asyncio.FIRST_COMPLETED)
    if getter in done:
        return getter.result()
    getter.cancel()
    task.result()
    raise StartupFailedError("the app ended its lifespan without a message")
