"""The S7 backend of the link seam: :class:`S7Link`, mvpose as the S7 client (PUT/GET) of the
line's PLC, started with the station file's ``links.s7`` settings.

The handshake is the bus-agnostic one (:mod:`drivers.links.handshake`) over the fieldbus layout
(:mod:`drivers.links.layout`, big-endian as S7 is); this module only moves its bytes: every poll
it reads the trigger DB and hands the whole output image to the handshake, then writes what
changed of the result DB (:class:`~drivers.links.s7.poller.ResultWriter`). A measurement's end
wakes the poll at once, so an answer waits for no poll period. A PLC that cannot be reached,
drops the connection or stops answering is connected to again with a growing wait, logged once
per outage; meanwhile its heartbeat stands still, so the handshake's watchdog reports it exactly
as the Modbus link's does (state ERROR, error WATCHDOG, ``plc_online`` false) and the station
shows it so. The handshake keeps its state across the outage: on reconnection the PLC is given
the whole result block again before the link counts as connected, so an answer published while
it was away is neither lost nor doubled (its result id and DONE_TOGGLE are the ones it was
published with), and a PLC never acts on the block as it stood before the outage.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, cast

from ..base import LinkOutcome, LinkRequest, StationHandler
from ..handshake import HandshakeConfig, HandshakeLink, HandshakeRunner
from ..layout import INPUT_FIELDS, INPUT_SIZE, IR_STATUS, OUTPUT_SIZE, ByteOrder, Status
from .poller import Backoff, Block, BlockError, Outage, ResultWriter, check_pdu
from .settings import S7LinkConfig
from .transport import AreaRefusedError, PlcLostError, S7Connection

log = logging.getLogger(__name__)

ORDER = ByteOrder.BIG  # every S7 value is big-endian


def _field(name: str) -> slice:
    for f in INPUT_FIELDS:
        if f.name == name:
            return slice(f.offset, f.offset + 2)
    raise LookupError(f"the layout's input block has no field {name!r}")


HEARTBEAT = _field("heartbeat")  # the device heartbeat word, written on its own when it moves


@dataclass
class S7Stats:
    """Counters of the S7 link's transport (the handshake has its own)."""

    connects: int = 0
    polls: int = 0
    block_writes: int = 0
    heartbeat_writes: int = 0
    block_errors: int = 0
    last_errors: list[str] = field(default_factory=list)


class _Waking:
    """The station's handler, with a measurement's end waking the poll loop (so the answer is
    written at once, not at the next poll). Everything else is the station's handler itself."""

    def __init__(self, inner: StationHandler, wake: Callable[[], None]) -> None:
        self._inner = inner
        self._wake = wake

    def measure(self, request: LinkRequest) -> Awaitable[LinkOutcome]:
        pending = asyncio.ensure_future(self._inner.measure(request))
        pending.add_done_callback(lambda _f: self._wake())
        return pending

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


class S7Link(HandshakeLink):
    """S7 client of the PLC: the trigger DB polled, the result DB written."""

    name = "s7"
    config: S7LinkConfig

    def __init__(self, config: S7LinkConfig, handler: StationHandler) -> None:
        super().__init__(config, handler)
        c = config
        self.trigger = Block("trigger", c.trigger_db, c.trigger_start, OUTPUT_SIZE)
        self.result = Block("result", c.result_db, c.result_start, INPUT_SIZE)
        self.outage = Outage()
        self.stats = S7Stats()
        self.pdu_size = 0
        self._writer = ResultWriter(self.result, HEARTBEAT)
        self._task: asyncio.Task[None] | None = None
        self._wake = asyncio.Event()
        self._stopping = False

    # ------------------------------------------------------------------ life cycle

    async def start(self) -> None:
        c = self.config
        hs = HandshakeConfig(
            word_order=ORDER.word_order, measure_timeout_s=c.measure_timeout_s or 0.0,
            watchdog_s=c.watchdog_s, trigger_hold_s=c.trigger_hold_s,
            initial_recipe=self.handler.selected_recipe())
        self._stopping = False
        runner = HandshakeRunner(cast(StationHandler, _Waking(self.handler, self._wake.set)),
                                 hs, link=self.name)
        await runner.start()
        self.runner = runner
        self._task = asyncio.create_task(self._run(runner), name="s7-link")

    async def stop(self) -> None:
        task, self._task = self._task, None
        self._stopping = True
        # Cancelled again until it ends: on Python 3.11 asyncio.wait_for (python-snap7 awaits
        # every receive with it) drops a cancellation that arrives as its read completes
        # (CPython gh-86296); the loops also end at their next pass when they see _stopping.
        while task is not None and not task.done():
            task.cancel()
            await asyncio.wait({task}, timeout=0.1)
        if task is not None and not task.cancelled():
            task.exception()  # retrieved: the loop ends by cancellation or by _stopping
        if self.runner is not None:
            await self.runner.stop()
            self.runner = None

    def ready(self) -> bool:
        # as the Modbus link: up while it runs; a lost PLC is the handshake's watchdog's to say
        return self.runner is not None

    def status(self) -> dict[str, Any]:
        if self.runner is None:
            return {"running": False}
        st = self.runner.stats
        machine = self.runner.machine
        image = self.runner.input_image(ORDER)
        c = self.config
        return {
            "running": True, "plc": f"{c.host}:{c.port}", "connected": self.outage.up,
            "trigger_db": str(self.trigger), "result_db": str(self.result),
            "pdu_size": self.pdu_size, "state": machine.state.name,
            "connects": self.stats.connects, "outages": self.outage.outages,
            "problem": self.outage.reason, "polls": self.stats.polls,
            "block_writes": self.stats.block_writes,
            "heartbeat_writes": self.stats.heartbeat_writes,
            "block_errors": self.stats.block_errors,
            "timeouts": st.timeouts, "handler_errors": st.handler_errors,
            "last_errors": [*self.stats.last_errors[-5:], *list(st.last_errors[-5:])][-5:],
            "server_heartbeat": int.from_bytes(image[HEARTBEAT], "big"),
            "plc_online": bool(machine.image[IR_STATUS] & Status.ONLINE),
            "error_code": int(machine.error),
            "result_id": machine.result_id,
            "watchdog_trips": st.handshake.watchdog_trips,
            "missed_triggers": st.handshake.missed_triggers,
        }

    # ------------------------------------------------------------------ the connection

    async def _run(self, runner: HandshakeRunner) -> None:
        c = self.config
        backoff = Backoff(c.reconnect_min_s, c.reconnect_max_s)
        while not self._stopping:
            conn = S7Connection(c.host, c.port, c.tsaps, c.request_timeout_s)
            try:
                await conn.open()
                self.pdu_size = conn.pdu_size
                check_pdu(conn.pdu_size, self.trigger, self.result, conn.plc)
                await conn.check_block(self.trigger)
                await conn.check_block(self.result)  # before any write: none lands half-way
                # The PLC's copy of the result block is as the link left it before an outage
                # (no ERROR, READY, however the handshake went on meanwhile): it is written
                # whole, from the handshake's image, before the link counts as connected, so a
                # PLC that acts once the link is back never reads the stale one.
                self._writer.reset()
                await self._publish(conn, runner)
                self._connected(conn)
                backoff.reset()
                await self._poll(conn, runner)
            except (PlcLostError, BlockError, AreaRefusedError) as err:
                self._lost(err)
            except Exception as err:  # noqa: BLE001 — a bug here must not end the link for good
                log.exception("S7 link: the poll loop failed")
                self._lost(PlcLostError(f"PLC {conn.plc}: the poll loop failed: {err!r}"))
            finally:
                await conn.close()
            await asyncio.sleep(backoff.next())

    def _connected(self, conn: S7Connection) -> None:
        self.stats.connects += 1
        if self.outage.connected():
            log.warning("S7 link: PLC %s reachable again (PDU %d bytes)", conn.plc,
                        conn.pdu_size)
        else:
            log.info("S7 link: connected to PLC %s (PDU %d bytes)", conn.plc, conn.pdu_size)

    def _lost(self, err: Exception) -> None:
        text = str(err)
        block = isinstance(err, BlockError | AreaRefusedError)
        self.stats.block_errors += block
        self.stats.last_errors = [*self.stats.last_errors[-9:], text]
        if self.outage.lost(text, "block" if block else "lost"):  # not once per attempt
            log.warning("S7 link: %s; connecting again every %g s at most", text,
                        self.config.reconnect_max_s)

    async def _poll(self, conn: S7Connection, runner: HandshakeRunner) -> None:
        loop = asyncio.get_running_loop()
        period = self.config.poll_s
        due = loop.time()
        while not self._stopping:
            outputs = await conn.read(self.trigger.db, self.trigger.start, self.trigger.size)
            self.stats.polls += 1
            runner.write_output(outputs, ORDER)  # edges start their work here
            await _passes()  # a quick answer (a refusal, a command) goes out with this write
            await self._publish(conn, runner)
            due = max(due + period, loop.time())
            woken = False
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout_at(due):
                    await self._wake.wait()
                    woken = True
            if woken:  # a measurement ended: its answer goes out now, the poll stays on time
                self._wake.clear()
                await _passes()
                await self._publish(conn, runner)
                await asyncio.sleep(max(0.0, due - loop.time()))

    async def _publish(self, conn: S7Connection, runner: HandshakeRunner) -> None:
        write = self._writer.next_write(runner.input_image(ORDER))
        if write is None:
            return
        await conn.write(write)
        self._writer.written(write)
        if len(write.data) == self.result.size:
            self.stats.block_writes += 1
        else:
            self.stats.heartbeat_writes += 1


async def _passes(n: int = 3) -> None:
    """A few loop passes: the runner publishes an outcome a pass or two after its future ends."""
    for _ in range(n):
        await asyncio.sleep(0)
