"""The EtherNet/IP adapter's sockets: a thin asyncio layer around :class:`.adapter.Adapter`.

TCP 44818 carries encapsulation (sessions, explicit messages, Forward Open / Close), UDP 44818
answers ListIdentity, UDP 2222 carries class 1 I/O both ways. One task paces the T→O
datagrams at each connection's API and checks the inactivity timeouts. Every event of the core
is logged here with the peer it concerns; output images go to ``on_outputs``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from ...errors import DriverInitError
from ..allowlist import Allowlist
from .adapter import (
    Adapter,
    ConnectionClosed,
    ConnectionOpened,
    OutputImage,
    Refused,
    TcpSession,
)
from .admission import Limits
from .codec import Identity
from .objects import Assemblies

log = logging.getLogger(__name__)

TICK_S = 0.005  # the longest the pacing task sleeps (timeouts are checked this often)
CHANGE_S = 0.001  # how often the image is compared for a change-of-state connection


@dataclass
class EnipStats:
    """Counters of the adapter's traffic (the status page shows them)."""

    sessions: int = 0
    rejected_peers: int = 0
    refused: int = 0
    opened: int = 0
    closed: int = 0
    timeouts: int = 0
    images: int = 0
    produced: int = 0
    last_errors: list[str] = field(default_factory=list)


class _Io(asyncio.DatagramProtocol):
    def __init__(self, owner: EnipServer, io: bool) -> None:
        self.owner = owner
        self.io = io
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str | int, ...]) -> None:
        self.owner._datagram(self, data, (str(addr[0]), int(addr[1])))


class EnipServer:
    """The adapter on TCP and UDP. ``inputs()`` is read for every T→O datagram and every Get
    on the input assembly; ``on_outputs(data)`` is called with every new output image."""

    def __init__(self, identity: Identity, inputs: Callable[[], bytes],
                 on_outputs: Callable[[bytes], None], assemblies: Assemblies | None = None,
                 limits: Limits | None = None, allowlist: tuple[str, ...] = (),
                 on_close: Callable[[ConnectionClosed], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.identity = identity
        self.assemblies = assemblies or Assemblies()
        self.limits = limits or Limits()
        self.inputs = inputs
        self.on_outputs = on_outputs
        self.on_close = on_close
        self.peers = Allowlist(allowlist)
        self.clock = clock
        self.stats = EnipStats()
        self.adapter: Adapter | None = None
        self._tcp: asyncio.Server | None = None
        self._io: _Io | None = None
        self._udp_encap: _Io | None = None
        self._pacer: asyncio.Task[None] | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._handlers: set[asyncio.Task[None]] = set()

    # --------------------------------------------------------------------- life cycle

    async def start(self, host: str = "127.0.0.1", port: int = 44818,
                    io_port: int = 2222) -> None:
        """Listen on TCP ``host:port`` (and UDP ``port`` for ListIdentity), UDP ``io_port``
        for I/O; 0 picks a free port (see ``port`` and ``io_port``)."""
        loop = asyncio.get_running_loop()
        try:
            self._tcp = await asyncio.start_server(self._serve, host, port)
            _, io = await loop.create_datagram_endpoint(lambda: _Io(self, True),
                                                        local_addr=(host, io_port))
        except OSError as err:
            await self.stop()
            raise DriverInitError(f"EtherNet/IP: {host} TCP {port} / UDP {io_port} cannot be "
                                  f"listened on ({err.strerror or err})") from err
        self._io = io
        try:
            _, self._udp_encap = await loop.create_datagram_endpoint(
                lambda: _Io(self, False), local_addr=(host, self.port))
        except OSError as err:  # ListIdentity on UDP is a convenience: say so, run without
            self._note(f"UDP {self.port} for ListIdentity cannot be bound ({err}); "
                       "ListIdentity is answered on TCP only")
        self.adapter = Adapter(self.identity, self.assemblies, self.limits, host, self.io_port,
                               self.port)
        self._pacer = asyncio.create_task(self._pace(), name="enip-io")

    @property
    def port(self) -> int:
        if self._tcp is None:
            raise RuntimeError("EnipServer not started")
        return int(self._tcp.sockets[0].getsockname()[1])

    @property
    def io_port(self) -> int:
        if self._io is None or self._io.transport is None:
            raise RuntimeError("EnipServer not started")
        return int(self._io.transport.get_extra_info("sockname")[1])

    async def stop(self) -> None:
        """Close every socket and stop pacing (open connections simply end: the scanner sees
        its connection time out, as when an adapter loses power)."""
        if self._pacer is not None:
            self._pacer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._pacer
            self._pacer = None
        if self._tcp is not None:
            self._tcp.close()
            for w in list(self._writers):
                w.close()  # each session's read ends (end of stream) and its task returns
            if self._handlers:
                await asyncio.wait(list(self._handlers), timeout=2.0)
            for task in list(self._handlers):  # one that did not: cancelled (it returns)
                task.cancel()
            if self._handlers:
                await asyncio.wait(list(self._handlers), timeout=2.0)
            await self._tcp.wait_closed()
            self._tcp = None
        for proto in (self._io, self._udp_encap):
            if proto is not None and proto.transport is not None:
                proto.transport.close()
        self._io = self._udp_encap = None

    # --------------------------------------------------------------------- TCP

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._handlers.add(task)
        peer = writer.get_extra_info("peername")
        host = str(peer[0]) if peer else ""
        try:
            if not self.peers.allows(host):
                self.stats.rejected_peers += 1
                self._note(f"connection from {host} refused (not in the allowlist)")
                return
            assert self.adapter is not None
            self._writers.add(writer)
            session = self.adapter.session(host)
            self.stats.sessions += 1
            await self._session(session, reader, writer)
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        except asyncio.CancelledError:
            # the server stops: end normally (asyncio's stream callback would otherwise log
            # the cancellation as an error)
            pass
        finally:
            self._writers.discard(writer)
            self._handlers.discard(task)
            writer.close()

    async def _session(self, session: TcpSession, reader: asyncio.StreamReader,
                       writer: asyncio.StreamWriter) -> None:
        try:
            while not session.closed:
                data = await reader.read(65536)
                if not data:
                    break
                assert self.adapter is not None
                self.adapter.inputs = bytes(self.inputs())  # a Get reads the image of now
                try:
                    replies = session.receive_data(data, self.clock())
                except Exception as err:  # noqa: BLE001 — a core fault ends this peer only
                    self._note(f"session of {session.peer} failed: {err!r}; connection closed")
                    break
                self._drain()
                for reply in replies:
                    writer.write(reply)
                await writer.drain()
        finally:
            session.close()
            self._drain()

    # --------------------------------------------------------------------- UDP

    def _datagram(self, proto: _Io, data: bytes, addr: tuple[str, int]) -> None:
        if self.adapter is None:
            return
        if not self.peers.allows(addr[0]):
            self.stats.rejected_peers += 1
            self._note(f"datagram from {addr[0]} dropped (not in the allowlist)")
            return
        if proto.io:
            self.adapter.receive_io(data, addr[0], self.clock())
        else:
            reply = self.adapter.receive_udp_encapsulation(data, addr[0])
            if reply is not None and proto.transport is not None:
                proto.transport.sendto(reply, addr)
        self._drain()

    async def _pace(self) -> None:
        adapter = self.adapter
        assert adapter is not None
        while True:
            now = self.clock()
            try:
                adapter.tick(now)
                due = adapter.next_due()
                watch = adapter.watches_changes()
                if due is not None and due <= now or watch:
                    out = adapter.produce(now, self.inputs())
                    if self._io is not None and self._io.transport is not None:
                        for datagram, dest in out:
                            self._io.transport.sendto(datagram, dest)
                    self.stats.produced += len(out)
                    due = adapter.next_due()
                self._drain()
            except Exception as err:  # noqa: BLE001 — one bad pass must not stop the I/O
                self._note(f"I/O pass failed: {err!r}")
                due = None
                watch = False
            longest = CHANGE_S if watch else TICK_S
            wait = longest if due is None else min(longest, max(0.0, due - self.clock()))
            await asyncio.sleep(wait)

    # --------------------------------------------------------------------- events

    def _drain(self) -> None:
        assert self.adapter is not None
        for ev in self.adapter.events():
            if isinstance(ev, OutputImage):
                self.stats.images += 1
                try:
                    self.on_outputs(ev.data)
                except Exception as err:  # noqa: BLE001 — the handshake reports its own faults
                    self._note(f"output image from {ev.peer} failed: {err!r}")
            elif isinstance(ev, Refused):
                self.stats.refused += 1
                self._note(f"{ev.what} from {ev.peer}: answered {ev.status}")
            elif isinstance(ev, ConnectionOpened):
                self.stats.opened += 1
                log.info("EtherNet/IP: class %d connection 0x%08X opened by %s (RPI %g ms)",
                         ev.transport_class, ev.connection_id, ev.peer, ev.rpi_ms)
            else:
                self.stats.closed += 1
                if ev.why == "timed out":
                    self.stats.timeouts += 1
                    self._note(f"class {ev.transport_class} connection 0x{ev.connection_id:08X} "
                               f"of {ev.peer} timed out (no packet within RPI × multiplier)")
                else:
                    log.info("EtherNet/IP: class %d connection 0x%08X of %s closed (%s)",
                             ev.transport_class, ev.connection_id, ev.peer, ev.why)
                if self.on_close is not None:
                    self.on_close(ev)

    def _note(self, text: str) -> None:
        log.warning("EtherNet/IP: %s", text)
        self.stats.last_errors = [*self.stats.last_errors[-9:], text]
