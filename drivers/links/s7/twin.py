"""The S7 side of the PLC twin: a CPU (python-snap7's own server) hosting the trigger and result
data blocks, and the port through which the twin's PLC program reads and writes them, as a PLC
program reads and writes its own DBs while mvpose, the S7 client, polls them over PUT/GET.

:class:`S7Cpu` is the PLC: it listens on a port (0: any free one), may be started and stopped
(a CPU going away and coming back), may drop its connections (a pulled cable), and can be built
with a DB missing, a DB too short, or a small PDU, for the tests of bad PLC projects.
:class:`S7Port` is what :class:`drivers.links.twin.PlcTwin` drives (its ``PlcPort``).
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Iterator
from typing import Any

from snap7.server import Server
from snap7.type import SrvArea

from ..layout import INPUT_SIZE, OUTPUT_SIZE, ByteOrder, WordOrder


class _Server(Server):
    """snap7's server, keeping its client sockets (to drop them) and, when asked, offering a
    PDU smaller than its own 480 bytes."""

    def __init__(self, max_pdu: int | None) -> None:
        super().__init__(log=False)
        self.max_pdu = max_pdu
        self.sockets: set[socket.socket] = set()
        self.sockets_lock = threading.Lock()

    def _handle_client(self, client_socket: socket.socket, address: Any) -> None:
        with self.sockets_lock:
            self.sockets.add(client_socket)
        try:
            super()._handle_client(client_socket, address)
        finally:
            with self.sockets_lock:
                self.sockets.discard(client_socket)

    def _handle_setup_communication(self, request: dict[str, Any]) -> bytes:
        answer = super()._handle_setup_communication(request)
        if self.max_pdu is None:
            return answer
        pdu = min(int.from_bytes(answer[-2:], "big"), self.max_pdu)
        return answer[:-2] + pdu.to_bytes(2, "big")

    def drop(self) -> int:
        with self.sockets_lock:
            dropped = list(self.sockets)
        for s in dropped:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
        return len(dropped)


class S7Cpu:
    """A PLC with the trigger DB and the result DB, reachable over ISO-on-TCP on loopback.

    ``trigger_db_size`` / ``result_db_size``: the DBs' lengths (default: start + block size;
    0: the DB does not exist). ``max_pdu``: the largest PDU the CPU negotiates."""

    def __init__(self, *, trigger_db: int = 100, trigger_start: int = 0, result_db: int = 101,
                 result_start: int = 0, trigger_db_size: int | None = None,
                 result_db_size: int | None = None, max_pdu: int | None = None,
                 host: str = "127.0.0.1") -> None:
        self.trigger_db, self.trigger_start = trigger_db, trigger_start
        self.result_db, self.result_start = result_db, result_start
        self.host = host
        self.max_pdu = max_pdu
        sizes = {trigger_db: trigger_start + OUTPUT_SIZE if trigger_db_size is None
                 else trigger_db_size}
        want = result_start + INPUT_SIZE if result_db_size is None else result_db_size
        sizes[result_db] = max(sizes.get(result_db, 0), want) if result_db == trigger_db else want
        self.dbs = {n: bytearray(size) for n, size in sizes.items() if size > 0}
        self._server: _Server | None = None
        self.port = 0

    def start(self) -> S7Cpu:
        """Listen (on the port it had before, after a stop: a CPU that comes back)."""
        if self._server is not None:
            return self
        server = _Server(self.max_pdu)
        for number, data in self.dbs.items():
            server.register_area(SrvArea.DB, number, data)
        server.start_to(self.host, self.port)
        assert server.server_socket is not None  # started
        self.port = int(server.server_socket.getsockname()[1])
        self._server = server
        return self

    def stop(self) -> None:
        """The CPU goes away: it stops listening and drops every connection."""
        server, self._server = self._server, None
        if server is not None:
            server.running = False  # snap7's stop() waits for its clients; drop them first
            server.drop()
            server.stop()

    def drop_connections(self) -> int:
        """Drop every client's connection (a pulled cable); the CPU keeps listening."""
        return 0 if self._server is None else self._server.drop()

    @property
    def connections(self) -> int:
        if self._server is None:
            return 0
        with self._server.sockets_lock:
            return len(self._server.sockets)

    def __enter__(self) -> S7Cpu:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def settings(self) -> dict[str, Any]:
        """The station file's ``links.s7`` block for this CPU."""
        return {"host": self.host, "port": self.port, "trigger_db": self.trigger_db,
                "trigger_start": self.trigger_start, "result_db": self.result_db,
                "result_start": self.result_start}

    @contextlib.contextmanager
    def _locked(self, db: int) -> Iterator[bytearray]:
        # the server's own lock of the DB: a client's read or write is never cut in half
        server = self._server
        if server is not None:
            server.lock_area(SrvArea.DB, db)
        try:
            yield self.dbs[db]
        finally:
            if server is not None:
                server.unlock_area(SrvArea.DB, db)

    def read(self, db: int, start: int, size: int) -> bytes:
        """Bytes of a DB, as the PLC program reads them (between two client requests)."""
        with self._locked(db) as data:
            return bytes(data[start: start + size])

    def write(self, db: int, start: int, chunk: bytes) -> None:
        """Bytes into a DB, as the PLC program writes them (between two client requests)."""
        with self._locked(db) as data:
            if start + len(chunk) > len(data):
                raise ValueError(f"DB{db} is {len(data)} bytes; cannot write {len(chunk)} "
                                 f"at {start}")
            data[start: start + len(chunk)] = chunk


class S7Port:
    """The twin's PLC program on an :class:`S7Cpu`: it reads the result block (its inputs) and
    writes the trigger block (its outputs) in the CPU's own memory; mvpose's S7 link polls the
    same bytes over the network. Big-endian, as every S7 value is."""

    byte_order = ByteOrder.BIG
    word_order = WordOrder.ABCD

    def __init__(self, cpu: S7Cpu) -> None:
        self.cpu = cpu

    async def connect(self) -> None:
        """The program starts on a running CPU."""
        if self.cpu.port == 0:
            raise RuntimeError("the S7 CPU is not started")

    async def read_inputs(self) -> bytes:
        return self.cpu.read(self.cpu.result_db, self.cpu.result_start, INPUT_SIZE)

    async def write_outputs(self, offset: int, data: bytes) -> None:
        if offset < 0 or offset + len(data) > OUTPUT_SIZE:
            raise ValueError(f"outputs {offset}..{offset + len(data) - 1} are outside the "
                             f"{OUTPUT_SIZE}-byte trigger block")
        self.cpu.write(self.cpu.trigger_db, self.cpu.trigger_start + offset, data)

    def close(self) -> None:
        """The program ends; the CPU (and mvpose's connection to it) stays."""

    def abort(self) -> None:
        """A pulled cable: the CPU drops mvpose's connection (the link connects again)."""
        self.cpu.drop_connections()
