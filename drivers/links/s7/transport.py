"""python-snap7's asyncio client, wrapped: the only module of the S7 backend that imports snap7's
client (the twin's module imports its server). Its exceptions become two of ours:
:class:`PlcLostError` (no connection, a timeout, a dropped socket: connect again) and
:class:`AreaRefusedError` (the PLC answered, refusing a read or write of a DB range).

python-snap7 3.x is pure Python (asyncio streams for ISO-on-TCP, RFC 1006 and ISO 8073 class 0,
and the S7comm PDUs); pinned in pyproject.toml, as its client API changed within 3.x.
"""

from __future__ import annotations

import asyncio
import contextlib

from snap7.async_client import AsyncClient, AsyncISOTCPConnection
from snap7.error import S7ConnectionError, S7Error, S7ProtocolError, S7TimeoutError

from ...errors import DeviceLostError, DriverOperationError
from .poller import Block, BlockError, DbWrite, ProbeLength, missing, too_short


class PlcLostError(DeviceLostError):
    """The PLC cannot be reached, or stopped answering: connect again."""


class AreaRefusedError(DriverOperationError):
    """The PLC answered a read or write of a DB range with an error (no such DB, out of range,
    no access)."""


class S7Connection:
    """One ISO-on-TCP connection to a PLC, one request at a time."""

    def __init__(self, host: str, port: int, tsaps: tuple[int, int], timeout_s: float) -> None:
        self.host, self.port = host, port
        self.local_tsap, self.remote_tsap = tsaps
        self.timeout_s = timeout_s
        self._client: AsyncClient | None = None

    @property
    def plc(self) -> str:
        """The PLC as messages name it."""
        return f"{self.host}:{self.port} (TSAP {self.remote_tsap:#06x})"

    @property
    def pdu_size(self) -> int:
        """The PDU size the PLC negotiated (Setup Communication)."""
        if self._client is None:
            raise PlcLostError(f"PLC {self.plc}: not connected")
        return int(self._client.pdu_length)

    async def open(self) -> None:
        """Connect (ISO connection request with our TSAPs, then S7 Setup Communication)."""
        client = AsyncClient()
        client.local_tsap, client.remote_tsap = self.local_tsap, self.remote_tsap
        conn = AsyncISOTCPConnection(self.host, self.port, local_tsap=self.local_tsap,
                                     remote_tsap=self.remote_tsap)
        client.connection = conn
        try:
            async with asyncio.timeout(self.timeout_s * 2):
                await conn.connect(timeout=self.timeout_s)
                # AsyncClient.connect() derives the remote TSAP from rack/slot; with a TSAP
                # of our own we run its two steps: the ISO connection, then this.
                await client._setup_communication()  # noqa: SLF001 - pinned python-snap7
        except (S7Error, OSError, TimeoutError) as err:
            await _quietly(client)
            raise PlcLostError(f"PLC {self.plc}: cannot connect: {_why(err)}") from err
        client.connected = True
        self._client = client

    async def close(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            await _quietly(client)

    def abort(self) -> None:
        """Drop the socket without the ISO disconnect (the loop is stopping)."""
        client, self._client = self._client, None
        if client is not None:
            _abort(client)

    async def read(self, db: int, start: int, size: int) -> bytes:
        client = self._connected()
        try:
            async with asyncio.timeout(self.timeout_s):
                return bytes(await client.db_read(db, start, size))
        except S7ProtocolError as err:
            raise AreaRefusedError(f"PLC {self.plc}: read of DB{db}.DBB{start} ({size} bytes) "
                              f"refused: {_why(err)}") from err
        except (S7ConnectionError, S7TimeoutError, S7Error, OSError, TimeoutError) as err:
            raise self._lost("read", err) from err

    async def write(self, w: DbWrite) -> None:
        client = self._connected()
        try:
            async with asyncio.timeout(self.timeout_s):
                await client.db_write(w.db, w.start, bytearray(w.data))
        except S7ProtocolError as err:
            raise AreaRefusedError(f"PLC {self.plc}: write of DB{w.db}.DBB{w.start} "
                              f"({len(w.data)} bytes) refused: {_why(err)}") from err
        except (S7ConnectionError, S7TimeoutError, S7Error, OSError, TimeoutError) as err:
            raise self._lost("write", err) from err

    async def check_block(self, block: Block) -> bytes:
        """Read the whole block; BlockError naming the DB and its length when the PLC refuses,
        found with 1-byte reads (PlcLostError when the connection fails meanwhile)."""
        try:
            return await self.read(block.db, block.start, block.size)
        except AreaRefusedError:
            pass
        probe = ProbeLength(block.end)
        while not probe.done:
            try:
                await self.read(block.db, probe.next_offset, 1)
                probe.answer(True)
            except AreaRefusedError:
                probe.answer(False)
        if probe.length == 0:
            raise missing(block, self.plc)
        if probe.length >= block.end:  # it reads byte by byte but not as a whole
            raise BlockError(f"PLC {self.plc}: DB{block.db} (the {block.role} block) refuses "
                             f"a read of bytes {block.start}..{block.end - 1} as a whole")
        raise too_short(block, probe.length, self.plc)

    def _connected(self) -> AsyncClient:
        if self._client is None:
            raise PlcLostError(f"PLC {self.plc}: not connected")
        return self._client

    def _lost(self, what: str, err: BaseException) -> PlcLostError:
        client, self._client = self._client, None
        if client is not None:
            _abort(client)
        return PlcLostError(f"PLC {self.plc}: {what} failed: {_why(err)}")


def _abort(client: AsyncClient) -> None:
    writer = getattr(client.connection, "_writer", None)  # python-snap7 keeps no public handle
    if writer is not None:
        writer.transport.abort()
    client.connected = False


async def _quietly(client: AsyncClient) -> None:
    with contextlib.suppress(Exception):
        async with asyncio.timeout(1.0):
            await client.disconnect()


def _why(err: BaseException) -> str:
    if isinstance(err, TimeoutError) and not str(err):
        return "no answer in time"
    return str(err) or type(err).__name__
