"""Modbus/TCP conformance of the PLC link, seen from outside: raw frames over a plain socket (exact
bytes), pyModbusTCP, and mbpoll (libmodbus) from Debian — docs/modbus.md, "Conformance"."""

# ruff: noqa: F811 — the `plc` fixture comes from plc_peers
from __future__ import annotations

import asyncio
import contextlib
import re
import socket
import struct
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from plc_peers import ServerFactory, plc  # noqa: F401
from pyModbusTCP.client import ModbusClient
from system_packages import ensure_commands

from drivers.links import layout as r
from drivers.links.modbus.server import HR_MIRROR
from drivers.links.modbus.transport import FRAME_TIMEOUT_S, MAX_LENGTH, MAX_PENDING, MIN_LENGTH

UNIT = 0x11  # not 0, 1 or 255, so an echo of the wrong byte shows
CLOSE_WITHIN_S = 2.0  # what the docs promise for a malformed frame
FLOAT_12345 = bytes.fromhex("42F6E666")  # input 46-47, word order ABCD
INT_123456789 = bytes.fromhex("075BCD15")  # input 48-49


def adu(tid: int, pdu: bytes, unit: int = UNIT, pid: int = 0, length: int | None = None) -> bytes:
    """A Modbus/TCP request: MBAP header (length computed unless given) + PDU."""
    return struct.pack(">HHHB", tid, pid, len(pdu) + 1 if length is None else length, unit) + pdu


def answer(tid: int, pdu: bytes, unit: int = UNIT) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def exception(tid: int, fc: int, code: int, unit: int = UNIT) -> bytes:
    """The exact exception ADU: function byte 0x80 | fc, one exception code."""
    return answer(tid, bytes([fc | 0x80, code]), unit)


def read(fc: int, address: int, count: int) -> bytes:
    return struct.pack(">BHH", fc, address, count)


def write_multiple(address: int, words: list[int], count: int | None = None,
                   byte_count: int | None = None) -> bytes:
    n = len(words) if count is None else count
    bc = 2 * len(words) if byte_count is None else byte_count
    return struct.pack(">BHHB", 16, address, n, bc) + b"".join(w.to_bytes(2, "big") for w in words)


def read_write(read_address: int, reads: int, write_address: int, words: list[int],
               writes: int | None = None) -> bytes:
    n = len(words) if writes is None else writes
    return struct.pack(">BHHHHB", 23, read_address, reads, write_address, n, 2 * len(words)) + (
        b"".join(w.to_bytes(2, "big") for w in words))


def registers(*words: int) -> bytes:
    return bytes([2 * len(words)]) + b"".join(w.to_bytes(2, "big") for w in words)


class Raw:
    """A plain TCP connection (Nagle off, so each write leaves as its own segment)."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer

    @classmethod
    async def open(cls, port: int) -> Raw:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.get_extra_info("socket").setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return cls(reader, writer)

    async def send(self, data: bytes) -> None:
        self.writer.write(data)
        await self.writer.drain()

    async def recv(self, n: int, timeout: float = 3.0) -> bytes:
        return await asyncio.wait_for(self.reader.readexactly(n), timeout)

    async def ask(self, request: bytes, expected: bytes) -> bytes:
        """Send one request and read as many bytes as the expected answer has."""
        await self.send(request)
        return await self.recv(len(expected))

    async def nothing_within(self, seconds: float) -> bool:
        try:
            data = await asyncio.wait_for(self.reader.read(1), seconds)
        except TimeoutError:
            return True
        raise AssertionError(f"unexpected bytes {data.hex(' ')}")

    async def until_closed(self, timeout: float) -> bytes:
        """Everything the server sends until it closes the connection (fails after timeout)."""
        return await asyncio.wait_for(self.reader.read(), timeout)

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(ConnectionError):
            await self.writer.wait_closed()


# --------------------------------------------------------------------------- exception codes

OUTSIDE_THE_MAP = {
    0x00: b"\x00\x00\x00\x01",
    0x01: read(1, 0, 1)[1:],  # read coils
    0x02: read(2, 0, 1)[1:],  # read discrete inputs
    0x05: b"\x00\x00\xff\x00",  # write single coil
    0x07: b"",  # read exception status
    0x08: b"\x00\x00\x12\x34",  # diagnostics, return query data
    0x0B: b"",  # get comm event counter
    0x0C: b"",  # get comm event log
    0x0F: b"\x00\x00\x00\x01\x01\x01",  # write multiple coils
    0x11: b"",  # report server id
    0x14: b"\x07\x06\x00\x00\x00\x01\x00\x01",  # read file record
    0x16: b"\x00\x01\xff\xff\x00\x00",  # mask write register
    0x18: b"\x00\x00",  # read FIFO queue
    0x2B: b"\x0e\x01\x00",  # encapsulated interface: read device identification
    0x41: b"\x00\x00",  # user-defined
    0x64: b"",
    0x7F: b"\x00",
    0x83: read(3, 0, 1)[1:],  # the exception range: its function byte stays 0x83
}


async def test_every_function_code_outside_the_map_gets_exception_01(plc: ServerFactory) -> None:
    server, _ = await plc(connect=False)
    conn = await Raw.open(server.port)
    try:
        for n, (fc, body) in enumerate(OUTSIDE_THE_MAP.items()):
            tid = 0xA000 + n
            want = exception(tid, fc, 0x01)
            got = await conn.ask(adu(tid, bytes([fc]) + body), want)
            assert got == want, f"fc {fc}: {got.hex(' ')}"
        # the connection still serves the map afterwards
        want = answer(7, bytes([4]) + registers(0x42F6, 0xE666))
        assert await conn.ask(adu(7, read(4, r.IR_TEST_FLOAT, 2)), want) == want
    finally:
        await conn.close()
    assert server.stats.rejected_requests == len(OUTSIDE_THE_MAP)


BAD_QUANTITY = {
    "fc3 count 0": read(3, 0, 0),
    "fc3 count 126": read(3, 0, 126),
    "fc4 count 0": read(4, 0, 0),
    "fc4 count 126": read(4, 0, 126),
    "fc4 count 65535": read(4, 0, 0xFFFF),
    "fc3 PDU one byte short": read(3, 0, 1)[:-1],
    "fc4 PDU one byte long": read(4, 0, 1) + b"\x00",
    "fc6 PDU one byte short": b"\x06\x00\x01\x00",
    "fc16 count 0": write_multiple(0, []),
    "fc16 count 124": write_multiple(0, [], count=124, byte_count=0),
    "fc16 byte count not 2N": write_multiple(1, [1, 2], byte_count=3),
    "fc16 fewer values than the byte count": write_multiple(1, [1, 2], byte_count=6),
    "fc16 no byte count": struct.pack(">BHH", 16, 0, 1),
    "fc23 read count 0": read_write(0, 0, 1, [5]),
    "fc23 read count 126": read_write(0, 126, 1, [5]),
    "fc23 write count 0": read_write(0, 1, 1, []),
    "fc23 write count 122": read_write(0, 1, 1, [5], writes=122),
}


async def test_bad_quantity_or_length_gets_exception_03(plc: ServerFactory) -> None:
    server, _ = await plc(connect=False)
    conn = await Raw.open(server.port)
    try:
        for n, (name, pdu) in enumerate(BAD_QUANTITY.items()):
            want = exception(0xB000 + n, pdu[0], 0x03)
            got = await conn.ask(adu(0xB000 + n, pdu), want)
            assert got == want, f"{name}: {got.hex(' ')}"
    finally:
        await conn.close()
    assert server.machine.holding[1] == 0, "a refused write changed a register"


async def test_largest_legal_quantities_are_checked_against_the_map(plc: ServerFactory) -> None:
    """At the protocol's limits the quantity is legal, so the answer is about addresses (02),
    and within the map a request is served, with its transaction and unit id echoed."""
    server, _ = await plc(connect=False)
    conn = await Raw.open(server.port)
    cases = [
        (adu(1, read(3, 0, 125)), exception(1, 3, 0x02)),
        (adu(2, read(4, 0, 125)), exception(2, 4, 0x02)),
        (adu(3, write_multiple(0, [0] * 123)), exception(3, 16, 0x02)),
        (adu(4, read_write(0, 125, 0, [0] * 121)), exception(4, 23, 0x02)),
        (adu(0xFFFF, read(4, r.IR_TEST_FLOAT, 4), unit=0xFF),
         answer(0xFFFF, bytes([4]) + registers(0x42F6, 0xE666, 0x075B, 0xCD15), unit=0xFF)),
        (adu(0, read(4, r.IR_TEST_FLOAT, 4), unit=0),
         answer(0, bytes([4]) + registers(0x42F6, 0xE666, 0x075B, 0xCD15), unit=0)),
        (adu(0x8001, read(3, HR_MIRROR + r.IR_TEST_FLOAT, 2), unit=0xFF),
         answer(0x8001, bytes([3]) + registers(0x42F6, 0xE666), unit=0xFF)),
    ]
    try:
        for n, (request, want) in enumerate(cases):
            got = await conn.ask(request, want)
            assert got == want, f"case {n}: {got.hex(' ')}"
    finally:
        await conn.close()


BAD_ADDRESS = {
    "fc3 after the writable block": read(3, r.HR_WRITABLE_COUNT, 1),
    "fc3 across the writable block's end": read(3, r.HR_WRITABLE_COUNT - 1, 2),
    "fc3 after the mirror": read(3, HR_MIRROR + r.IR_COUNT, 1),
    "fc4 after the input registers": read(4, r.IR_COUNT, 1),
    "fc4 at the top of the address space": read(4, 0xFFFF, 1),
    "fc6 to the read-only mirror": struct.pack(">BHH", 6, HR_MIRROR + 3, 1),
    "fc6 after the writable block": struct.pack(">BHH", 6, r.HR_WRITABLE_COUNT, 1),
    "fc16 across the writable block's end": write_multiple(r.HR_WRITABLE_COUNT - 1, [1, 2]),
    "fc23 write after the writable block": read_write(0, 1, r.HR_WRITABLE_COUNT, [1]),
    "fc23 read after the mirror": read_write(HR_MIRROR + r.IR_COUNT, 1, 7, [0x0707]),
    "fc23 write to the mirror": read_write(0, 1, HR_MIRROR, [1]),
}


async def test_bad_address_gets_exception_02(plc: ServerFactory) -> None:
    server, _ = await plc(connect=False)
    conn = await Raw.open(server.port)
    try:
        for n, (name, pdu) in enumerate(BAD_ADDRESS.items()):
            want = exception(0xC000 + n, pdu[0], 0x02)
            got = await conn.ask(adu(0xC000 + n, pdu), want)
            assert got == want, f"{name}: {got.hex(' ')}"
    finally:
        await conn.close()
    # nothing was written by a refused request (fc 23 included: its write comes first)
    assert server.machine.holding == [0] * r.HR_WRITABLE_COUNT
    assert server.stats.writes == 0


async def test_unit_id_not_answered_gets_exception_0b(plc: ServerFactory) -> None:
    server, _ = await plc(connect=False, unit_id=1)
    conn = await Raw.open(server.port)
    try:
        want = exception(5, 4, 0x0B, unit=2)
        assert await conn.ask(adu(5, read(4, 0, 1), unit=2), want) == want
        want = answer(6, bytes([4]) + registers(0x075B, 0xCD15), unit=1)
        assert await conn.ask(adu(6, read(4, r.IR_TEST_INT, 2), unit=1), want) == want
    finally:
        await conn.close()


# --------------------------------------------------------------------------- malformed frames

READ_ADU = adu(0x0101, read(4, r.IR_TEST_INT, 2))
READ_ANSWER = answer(0x0101, bytes([4]) + registers(0x075B, 0xCD15))

MALFORMED = {
    # name: (bytes sent, bytes answered before the close, words in the server's note)
    "protocol id 1": (adu(1, read(4, 0, 1), pid=1), b"", "protocol id 1"),
    "protocol id after a good request": (READ_ADU + adu(2, read(4, 0, 1), pid=0x2F20),
                                         READ_ANSWER, "protocol id 12064"),
    "length 0": (adu(1, b"", length=0)[:6], b"", "MBAP length 0"),
    "length 1": (adu(1, b"", length=1), b"", "MBAP length 1"),
    "length 255": (adu(1, b"\x04" + bytes(253), length=255), b"", "MBAP length 255"),
    "length 65535": (adu(1, read(4, 0, 1), length=0xFFFF), b"", "MBAP length 65535"),
    "length beyond the data sent": (adu(1, read(4, 0, 1), length=12), b"", "incomplete frame"),
    "length short of the PDU": (adu(3, read(4, 0, 1), length=4), exception(3, 4, 0x03),
                                "incomplete frame"),
    "HTTP request": (b"GET / HTTP/1.1\r\nHost: plc\r\n\r\n", b"", "protocol id 21536"),
    "one stray byte": (b"\x00", b"", "incomplete frame (1 bytes"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
async def test_malformed_frame_closes_its_connection_only(plc: ServerFactory, case: str) -> None:
    sent, answered, note = MALFORMED[case]
    server, _ = await plc(connect=False)
    other = await Raw.open(server.port)
    bad = await Raw.open(server.port)
    try:
        assert await other.ask(READ_ADU, READ_ANSWER) == READ_ANSWER
        t0 = time.monotonic()
        await bad.send(sent)
        got = await bad.until_closed(CLOSE_WITHIN_S + 1.0)
        took = time.monotonic() - t0
        assert got == answered, f"{case}: {got.hex(' ')}"
        assert took < CLOSE_WITHIN_S, f"{case}: closed after {took:.2f} s"
        # the other connection goes on, and a new one is served
        for _ in range(3):
            assert await other.ask(READ_ADU, READ_ANSWER) == READ_ANSWER
        again = await Raw.open(server.port)
        try:
            assert await again.ask(READ_ADU, READ_ANSWER) == READ_ANSWER
        finally:
            await again.close()
    finally:
        await bad.close()
        await other.close()
    assert any(note in e for e in server.stats.last_errors), server.stats.last_errors


async def test_incomplete_frame_waits_the_frame_timeout_first(plc: ServerFactory) -> None:
    """A frame still arriving is not cut early: the close comes after FRAME_TIMEOUT_S."""
    server, _ = await plc(connect=False)
    bad = await Raw.open(server.port)
    try:
        t0 = time.monotonic()
        await bad.send(READ_ADU[:5])
        assert await bad.until_closed(CLOSE_WITHIN_S + 1.0) == b""
        assert FRAME_TIMEOUT_S <= time.monotonic() - t0 < CLOSE_WITHIN_S
    finally:
        await bad.close()


# --------------------------------------------------------------------------- pipelining


async def test_pipelined_requests_in_one_segment_are_answered_in_order(plc: ServerFactory) -> None:
    server, _ = await plc(connect=False)
    requests = [
        (adu(1, read(4, r.IR_TEST_FLOAT, 2)), answer(1, b"\x04" + registers(0x42F6, 0xE666))),
        (adu(2, struct.pack(">BHH", 6, r.HR_PART_ID, 0x4142)),
         answer(2, struct.pack(">BHH", 6, r.HR_PART_ID, 0x4142))),
        (adu(3, read(3, r.HR_PART_ID, 1)), answer(3, b"\x03" + registers(0x4142))),
        (adu(4, b"\x08\x00\x00\x12\x34"), exception(4, 8, 0x01)),
        (adu(5, read(3, 0, 0)), exception(5, 3, 0x03)),
        (adu(6, write_multiple(r.HR_PART_ID, [0x4344, 0x4546])),
         answer(6, struct.pack(">BHH", 16, r.HR_PART_ID, 2))),
        (adu(7, read_write(r.HR_PART_ID, 2, r.HR_PART_ID + 2, [0x4748])),
         answer(7, b"\x17" + registers(0x4344, 0x4546))),
        (adu(8, read(4, r.IR_COUNT, 1)), exception(8, 4, 0x02)),
        (adu(9, read(4, r.IR_TEST_INT, 2)), answer(9, b"\x04" + registers(0x075B, 0xCD15))),
    ]
    conn = await Raw.open(server.port)
    try:
        want = b"".join(a for _, a in requests)
        await conn.send(b"".join(q for q, _ in requests))
        got = await conn.recv(len(want))
        assert got == want, got.hex(" ")
        assert await conn.nothing_within(0.05)
    finally:
        await conn.close()
    assert server.machine.holding[r.HR_PART_ID : r.HR_PART_ID + 3] == [0x4344, 0x4546, 0x4748]


async def test_a_burst_of_pipelined_reads_is_answered_in_order(plc: ServerFactory) -> None:
    """200 requests in one write: far more than one receive buffer of pymodbus (264 bytes) and
    than the pending limit, so back-pressure is crossed both ways (a write first: the reads
    behind it wait in the queue instead of being answered at once)."""
    server, _ = await plc(connect=False)
    conn = await Raw.open(server.port)
    n = 200
    write = struct.pack(">BHH", 6, r.HR_PART_ID, 0x4142)
    try:
        await conn.send(adu(1, write) + b"".join(adu(t, read(4, r.IR_TEST_INT, 2))
                                                 for t in range(2, n + 1)))
        want = answer(1, write) + b"".join(answer(t, b"\x04" + registers(0x075B, 0xCD15))
                                           for t in range(2, n + 1))
        got = await conn.recv(len(want), timeout=10.0)
        assert got == want
    finally:
        await conn.close()


async def test_reads_answered_at_once_are_the_data_stores_answers(plc: ServerFactory) -> None:
    """A register read with nothing waiting before it is answered in the pass that received it
    (the input block and its holding-register mirror, from the handshake's image): the same
    bytes the queued path answers, and a range past the block still gets exception 02."""
    server, _ = await plc(connect=False)
    test_words = registers(0x42F6, 0xE666, 0x075B, 0xCD15)
    conn = await Raw.open(server.port)
    try:
        for tid, (fc, address) in enumerate(((4, r.IR_TEST_FLOAT),
                                             (3, HR_MIRROR + r.IR_TEST_FLOAT)), 1):
            want = answer(tid, bytes([fc]) + test_words)
            assert await conn.ask(adu(tid, read(fc, address, 4)), want) == want
        for tid, (fc, address) in enumerate(((4, r.IR_COUNT - 1), (3, HR_MIRROR + r.IR_COUNT - 1)),
                                            3):
            want = exception(tid, fc, 0x02)
            assert await conn.ask(adu(tid, read(fc, address, 2)), want) == want
        # the same read queued behind a write: the same answer
        write = struct.pack(">BHH", 6, r.HR_PART_ID, 0x4142)
        want = answer(5, write) + answer(6, b"\x04" + test_words)
        await conn.send(adu(5, write) + adu(6, read(4, r.IR_TEST_FLOAT, 4)))
        assert await conn.recv(len(want)) == want
    finally:
        await conn.close()


async def test_an_adu_split_across_segments_is_answered_once_complete(plc: ServerFactory) -> None:
    server, _ = await plc(connect=False)
    first = adu(0x0201, read(4, r.IR_TEST_FLOAT, 2))
    second = adu(0x0202, write_multiple(r.HR_PART_ID, [0x5A5A, 0x0102, 0x0304]))
    third = adu(0x0203, read(3, r.HR_PART_ID, 3))
    stream = first + second + third
    cuts = [2, 5, 7, len(first) + 9, len(first) + len(second) + 1]
    conn = await Raw.open(server.port)
    try:
        await conn.send(stream[: cuts[0]])
        assert await conn.nothing_within(0.05)
        for a, b in zip(cuts, [*cuts[1:], len(stream)], strict=True):
            await conn.send(stream[a:b])
            if b < len(first):
                assert await conn.nothing_within(0.05)  # no answer to half a request
        want = (answer(0x0201, b"\x04" + registers(0x42F6, 0xE666))
                + answer(0x0202, struct.pack(">BHH", 16, r.HR_PART_ID, 3))
                + answer(0x0203, b"\x03" + registers(0x5A5A, 0x0102, 0x0304)))
        got = await conn.recv(len(want))
        assert got == want, got.hex(" ")
    finally:
        await conn.close()


async def test_answers_are_sent_before_a_half_close(plc: ServerFactory) -> None:
    """A master that sends its requests and shuts its sending side still gets every answer."""
    server, _ = await plc(connect=False)
    conn = await Raw.open(server.port)
    try:
        await conn.send(READ_ADU + adu(0x0102, b"\x11") + READ_ADU)
        conn.writer.write_eof()
        got = await conn.until_closed(CLOSE_WITHIN_S)
        assert got == READ_ANSWER + exception(0x0102, 0x11, 0x01) + READ_ANSWER
    finally:
        await conn.close()


# --------------------------------------------------------------------------- independent masters


class TracingClient(ModbusClient):
    """pyModbusTCP's client, keeping the frames it receives."""

    def __init__(self, port: int, unit_id: int) -> None:
        super().__init__(host="127.0.0.1", port=port, unit_id=unit_id, auto_open=True,
                         timeout=2.0)
        self.received: list[bytes] = []

    def on_tx_rx(self, frame: bytes, is_tx: bool) -> None:
        if not is_tx:
            self.received.append(bytes(frame))


async def test_pymodbustcp_sees_the_exceptions(plc: ServerFactory) -> None:
    server, _ = await plc(connect=False)
    client = TracingClient(server.port, unit_id=255)

    def master() -> list[tuple[str, bytes | None, int, bytes]]:
        out = []
        for name, pdu in [
            ("read exception status", b"\x07"),
            ("diagnostics", b"\x08\x00\x00\xab\xcd"),
            ("report server id", b"\x11"),
            ("read FIFO", b"\x18\x00\x00"),
            ("device identification", b"\x2b\x0e\x01\x00"),
            ("read coils", b"\x01\x00\x00\x00\x01"),
            ("read 0 registers", b"\x03\x00\x00\x00\x00"),
            ("read 126 registers", b"\x04\x00\x00\x00\x7e"),
            ("read past the map", b"\x04\x00\x54\x00\x01"),  # input 84
            ("read the test values", b"\x04\x00\x2e\x00\x04"),
        ]:
            got = client.custom_request(pdu)
            out.append((name, got, client.last_except, client.received[-1][7:]))
        return out

    try:
        with ThreadPoolExecutor(1) as pool:
            seen = await asyncio.get_running_loop().run_in_executor(pool, master)
    finally:
        client.close()
    for name, got, last_except, _ in seen[:6]:
        assert (got, last_except) == (None, 1), name
    assert [p for *_, p in seen[:6]] == [bytes([fc, 1]) for fc in (0x87, 0x88, 0x91, 0x98, 0xAB,
                                                                   0x81)]
    assert [(e, p) for _, _, e, p in seen[6:9]] == [(3, b"\x83\x03"), (3, b"\x84\x03"),
                                                     (2, b"\x84\x02")]
    assert seen[9][1] == b"\x04\x08" + FLOAT_12345 + INT_123456789


def _mbpoll(port: int, *args: str) -> tuple[int, str]:
    proc = subprocess.run(
        ["mbpoll", "-m", "tcp", "-p", str(port), "-o", "2", "-0", "-1", *args],
        capture_output=True, text=True, timeout=30, check=False)
    return proc.returncode, proc.stdout + proc.stderr


async def test_mbpoll_reads_input_and_writes_holding_registers(plc: ServerFactory) -> None:
    ensure_commands({"mbpoll": "mbpoll"})
    server, _ = await plc(connect=False)
    port = server.port
    host = "127.0.0.1"
    runs = [
        ("float", ["-a", "255", "-t", "3:float", "-B", "-r", "46", host]),
        ("int", ["-a", "1", "-t", "3:int", "-B", "-r", "48", host]),
        ("words", ["-a", "0", "-t", "3:hex", "-r", "44", "-c", "6", host]),
        ("write many", ["-a", "1", "-t", "4", "-r", "20", host, "16706", "17220"]),  # fc 16
        ("write one", ["-a", "1", "-t", "4", "-r", "1", host, "7"]),  # fc 6
        ("read back", ["-a", "1", "-t", "4:hex", "-r", "20", "-c", "2", host]),
        ("mirror", ["-a", "1", "-t", "4:float", "-B", "-r", "146", host]),
        ("write the mirror", ["-a", "1", "-t", "4", "-r", "100", host, "5"]),
        ("coils", ["-a", "1", "-t", "0", "-r", "0", host]),
        ("discrete inputs", ["-a", "1", "-t", "1", "-r", "0", host]),
        ("past the map", ["-a", "1", "-t", "3", "-r", "0", "-c", "85", host]),
    ]

    def master() -> dict[str, tuple[int, str]]:
        return {name: _mbpoll(port, *args) for name, args in runs}

    with ThreadPoolExecutor(1) as pool:
        out = await asyncio.get_running_loop().run_in_executor(pool, master)
    for name in ("float", "int", "words", "write many", "write one", "read back", "mirror"):
        assert out[name][0] == 0, f"mbpoll {name}: {out[name][1]}"
    assert "[46]: \t123.45" in out["float"][1]
    assert "[48]: \t123456789" in out["int"][1]
    for line in ("[44]: \t0x0001", "[45]: \t0x0000", "[46]: \t0x42F6", "[49]: \t0xCD15"):
        assert line in out["words"][1]
    assert "Written 2 references" in out["write many"][1]
    assert "[20]: \t0x4142" in out["read back"][1] and "[21]: \t0x4344" in out["read back"][1]
    assert "[146]: \t123.45" in out["mirror"][1]
    assert server.machine.holding[r.HR_HEARTBEAT] == 7
    assert server.machine.holding[r.HR_PART_ID : r.HR_PART_ID + 2] == [0x4142, 0x4344]
    assert out["write the mirror"][0] != 0 and "Illegal data address" in out["write the mirror"][1]
    assert out["coils"][0] != 0 and "Illegal function" in out["coils"][1]
    assert out["discrete inputs"][0] != 0 and "Illegal function" in out["discrete inputs"][1]
    assert out["past the map"][0] != 0 and "Illegal data address" in out["past the map"][1]


def test_the_conformance_section_matches_this_module() -> None:
    """docs/modbus.md, "Conformance": every test it cites exists, and its numbers are the
    transport's."""
    doc = (Path(__file__).resolve().parents[2] / "docs" / "modbus.md").read_text()
    section = doc.split("## Conformance", 1)[1].split("\n## ", 1)[0]
    cited = set(re.findall(r"`(test_\w+)`", section))
    here = {name for name in globals() if name.startswith("test_")}
    assert cited - {"test_exception_codes_seen_by_pymodbustcp"} <= here, cited - here
    assert here - {"test_the_conformance_section_matches_this_module"} <= cited, here - cited
    assert f"complete {FRAME_TIMEOUT_S:g} s after its first byte" in section.replace("\n", " ")
    assert f"with {MAX_PENDING} requests not yet" in section.replace("\n", " ")
    assert f"MBAP length outside {MIN_LENGTH}..{MAX_LENGTH}" in section.replace("\n", " ")
    assert "test_exception_codes_seen_by_pymodbustcp" in Path(
        __file__).with_name("test_plc_independent.py").read_text()
