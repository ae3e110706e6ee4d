"""Modbus/TCP framing for the PLC link: MBAP checks, request checks, answers in order.

pymodbus 3.16's server connection (``ServerRequestHandler`` on ``FramerSocket``) keeps one decoded
request at a time (``last_pdu``), so a second ADU in the same TCP segment waits for bytes that may
never come, and its ``send`` empties the receive buffer; a non-zero protocol id makes the framer
wait for more data for good (the connection hangs); a function code it cannot decode, or a read
quantity out of range, is answered with function byte 0x80 and exception 01; every function code
it knows (diagnostics, report server id, FIFO, device identification, ...) is served. This module
replaces that receive path and keeps pymodbus's PDU classes and data store for the work:

- every complete ADU in the buffer is taken, in order; each gets exactly one answer, in order;
- the MBAP header is checked (protocol id 0, length 2..254); a bad header closes the connection
  (after the answers to the ADUs before it), and so does a frame left incomplete for
  ``FRAME_TIMEOUT_S``, so garbage can never wedge a connection;
- function codes outside ``function_codes`` get exception 01 with function byte ``0x80 | fc``; a
  quantity, byte count or PDU length outside the Modbus Application Protocol's limits gets 03;
  addresses are the data store's business (02), as before (fc 23's read range is checked
  before its write, so a refused request changes nothing); a unit id the data store has no
  device for gets 0B (gateway target failed to respond), as pymodbus answers it.

A register read that finds nothing else waiting on its connection is answered at once, in the
pass that received it, when the subclass's ``read_now`` has the words (the PLC link's input
block): a PLC polls its status every few milliseconds, and each poll answered through pymodbus's
request objects, data store and framer held the process's GIL about three times as long, beside
a running measurement.

Limits (Modbus Application Protocol V1.1b3, section 6): fc 3/4 read 1..125 registers, fc 6 has
a fixed 4-byte body, fc 16 writes 1..123 registers with byte count 2N, fc 23 reads 1..125 and
writes 1..121 registers with byte count 2N.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
from collections.abc import Callable
from typing import ClassVar

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.register_message import ReadWriteMultipleRegistersRequest
from pymodbus.server.base import ModbusBaseServer
from pymodbus.server.requesthandler import ServerRequestHandler

log = logging.getLogger(__name__)

MBAP = struct.Struct(">HHHB")  # transaction id, protocol id, length, unit id
READ = struct.Struct(">HH")  # a read request's starting address and quantity
MBAP_SIZE = MBAP.size  # 7
#: The MBAP length counts the unit id and the PDU: 2 (unit id + function code) to 254 (a PDU of
#: at most 253 bytes), so an ADU is at most 260 bytes.
MIN_LENGTH, MAX_LENGTH = 2, 254
#: An ADU that has started must be complete within this time, else the connection is closed. A
#: master writes each ADU at once; a gap this long means a length field that promises more bytes
#: than are coming (or a dead peer in the middle of a frame).
FRAME_TIMEOUT_S = 1.0
#: Requests taken but not yet answered on one connection before reading pauses (back-pressure
#: against a master that pipelines without bound).
MAX_PENDING = 32


def _registers_read(body: bytes) -> bool:
    return len(body) == 4 and 1 <= int.from_bytes(body[2:4], "big") <= 125


def _register_written(body: bytes) -> bool:
    return len(body) == 4


def _registers_written(body: bytes) -> bool:
    if len(body) < 5:
        return False
    count, byte_count = int.from_bytes(body[2:4], "big"), body[4]
    return 1 <= count <= 123 and byte_count == 2 * count and len(body) == 5 + byte_count


def _registers_read_written(body: bytes) -> bool:
    if len(body) < 9:
        return False
    reads, writes = int.from_bytes(body[2:4], "big"), int.from_bytes(body[6:8], "big")
    byte_count = body[8]
    return (
        1 <= reads <= 125
        and 1 <= writes <= 121
        and byte_count == 2 * writes
        and len(body) == 9 + byte_count
    )


#: Function code → check of the request body (the PDU after the function code): quantities,
#: byte count and length within the protocol's limits.
REQUEST_SHAPES: dict[int, Callable[[bytes], bool]] = {
    3: _registers_read,
    4: _registers_read,
    6: _register_written,
    16: _registers_written,
    23: _registers_read_written,
}

_CLOSE = None  # queue marker: close the connection once everything before it is answered


class ModbusTcpConnection(ServerRequestHandler):
    """One Modbus/TCP connection of a pymodbus server, with a conformant receive path.

    Subclasses narrow ``function_codes`` (each must be in ``REQUEST_SHAPES``) and may override
    ``rejected`` and ``malformed`` to count and report.
    """

    function_codes: ClassVar[frozenset[int]] = frozenset(REQUEST_SHAPES)
    frame_timeout_s: ClassVar[float] = FRAME_TIMEOUT_S

    def __init__(
        self,
        owner: ModbusBaseServer,
        trace_packet: Callable[[bool, bytes], bytes] | None,
        trace_pdu: Callable[[bool, ModbusPDU], ModbusPDU] | None,
        trace_connect: Callable[[bool], None] | None,
    ) -> None:
        super().__init__(owner, trace_packet, trace_pdu, trace_connect)
        unknown = self.function_codes - REQUEST_SHAPES.keys()
        if unknown:
            raise ValueError(f"{type(self).__name__}.function_codes: no request check for "
                             f"{sorted(unknown)}")
        self._rx = bytearray()
        self._queue: asyncio.Queue[tuple[int, int, int, ModbusPDU | ExcCodes] | None] = (
            asyncio.Queue())
        self._worker: asyncio.Task[None] | None = None
        self._frame_timer: asyncio.TimerHandle | None = None
        self._ending = False  # no more requests are taken (bad frame, EOF, closing)
        self._paused = False
        self._unanswered = 0  # requests queued and not yet answered (answers keep their order)
        self._traced = trace_packet is not None or trace_pdu is not None

    # ------------------------------------------------------------------ hooks

    def rejected(self, function_code: int, code: ExcCodes) -> None:
        """Called for every request answered with an exception by this layer."""

    def malformed(self, why: str) -> None:
        """Called when a frame cannot be Modbus/TCP; the connection is then closed."""
        log.warning("Modbus/TCP from %s: %s; closing the connection", self.peer(), why)

    def read_now(self, function_code: int, address: int, count: int) -> list[int] | None:
        """The ``count`` registers at ``address`` that function code 3 or 4 reads, if the
        subclass can give them without the data store (None: the request takes the data
        store's path, which also answers an illegal address)."""
        return None

    def peer(self) -> str:
        info = self.transport.get_extra_info("peername") if self.transport else None
        return f"{info[0]}:{info[1]}" if info else "?"

    # ------------------------------------------------------------------ receive

    def data_received(self, data: bytes) -> None:
        # Replaces ModbusProtocol.data_received (one ADU per call, buffer cut at 264 bytes).
        if self._ending:
            return
        self._rx += data
        taken = False
        while len(self._rx) >= 4:
            tid, pid = int.from_bytes(self._rx[0:2], "big"), int.from_bytes(self._rx[2:4], "big")
            if pid != 0:
                self._bad_frame(f"protocol id {pid} in the MBAP header of transaction {tid}, "
                                "expected 0")
                return
            if len(self._rx) < 6:
                break
            length = int.from_bytes(self._rx[4:6], "big")
            if not MIN_LENGTH <= length <= MAX_LENGTH:
                self._bad_frame(f"MBAP length {length} in transaction {tid}, expected "
                                f"{MIN_LENGTH}..{MAX_LENGTH}")
                return
            end = 6 + length
            if len(self._rx) < end:
                break
            uid, pdu = self._rx[6], bytes(self._rx[MBAP_SIZE:end])
            del self._rx[:end]
            taken = True
            if not self._unanswered and self._read_at_once(tid, uid, pdu):
                continue
            self._enqueue((tid, uid, pdu[0], self._request(tid, uid, pdu)))
        if taken or not self._rx:
            self._cancel_frame_timer()
        if self._rx and self._frame_timer is None:
            self._frame_timer = self.loop.call_later(self.frame_timeout_s, self._frame_expired)

    def eof_received(self) -> bool:  # type: ignore[override]  # asyncio: True keeps it open
        # The master closed its sending side: answer what it sent, then close.
        if not self._ending:
            self._ending = True
            self._cancel_frame_timer()
            self._enqueue(_CLOSE)
        return True

    def _read_at_once(self, tid: int, uid: int, pdu: bytes) -> bool:
        """Answer a register read now, if nothing is waiting before it and ``read_now`` has
        the words; False: it takes the queue."""
        fc = pdu[0]
        if (fc not in (3, 4) or fc not in self.function_codes or self._traced
                or self.transport is None or not _registers_read(pdu[1:])):
            return False
        units = self.server.context.device_ids()
        if 0 not in units and uid not in units:
            return False
        address, count = READ.unpack_from(pdu, 1)
        words = self.read_now(fc, address, count)
        if words is None or len(words) != count:
            return False
        body = struct.pack(f">BB{count}H", fc, 2 * count, *words)
        self.transport.write(MBAP.pack(tid, 0, len(body) + 1, uid) + body)  # type: ignore[attr-defined]
        return True

    def _request(self, tid: int, uid: int, pdu: bytes) -> ModbusPDU | ExcCodes:
        fc = pdu[0]
        units = self.server.context.device_ids()
        if 0 not in units and uid not in units:  # device 0 answers every unit id
            return self._reject(fc, ExcCodes.GATEWAY_NO_RESPONSE)
        if fc not in self.function_codes:
            return self._reject(fc, ExcCodes.ILLEGAL_FUNCTION)
        if not REQUEST_SHAPES[fc](pdu[1:]):
            return self._reject(fc, ExcCodes.ILLEGAL_VALUE)
        request = self.server.decoder.decode(pdu)
        if request is None:  # the shape was checked: pymodbus disagrees with the protocol
            log.error("Modbus/TCP: pymodbus could not decode function code %d: %s", fc, pdu.hex())
            return ExcCodes.DEVICE_FAILURE
        request.transaction_id, request.dev_id = tid, uid
        return request

    def _reject(self, fc: int, code: ExcCodes) -> ExcCodes:
        self.rejected(fc, code)
        return code

    def _bad_frame(self, why: str) -> None:
        self._ending = True
        self._rx.clear()
        self._cancel_frame_timer()
        self.malformed(why)
        self._enqueue(_CLOSE)

    def _frame_expired(self) -> None:
        self._frame_timer = None
        if self._rx and not self._ending:
            self._bad_frame(f"incomplete frame ({len(self._rx)} bytes: "
                            f"{bytes(self._rx[:16]).hex(' ')}) for {self.frame_timeout_s} s")

    def _cancel_frame_timer(self) -> None:
        if self._frame_timer is not None:
            self._frame_timer.cancel()
            self._frame_timer = None

    # ------------------------------------------------------------------ answer, in order

    def _enqueue(self, item: tuple[int, int, int, ModbusPDU | ExcCodes] | None) -> None:
        self._unanswered += 1
        self._queue.put_nowait(item)
        if self._worker is None:
            self._worker = self.loop.create_task(self._answer(), name=f"modbus-conn-{self.peer()}")
        if not self._paused and self._queue.qsize() >= MAX_PENDING and self.transport:
            self._paused = True
            self.transport.pause_reading()  # type: ignore[attr-defined]

    async def _answer(self) -> None:
        while True:
            item = await self._queue.get()
            if self._paused and self._queue.qsize() < MAX_PENDING // 2 and self.transport:
                self._paused = False
                self.transport.resume_reading()  # type: ignore[attr-defined]
            if item is _CLOSE:
                self.close()
                return
            tid, uid, fc, work = item
            if isinstance(work, ExcCodes):
                response: ModbusPDU = ExceptionResponse(fc, work)
            else:
                try:
                    response = await self._execute(work, uid)
                except Exception:  # noqa: BLE001 — one failed request must not end the link
                    log.exception("Modbus/TCP: function code %d from %s failed", fc, self.peer())
                    response = ExceptionResponse(fc, ExcCodes.DEVICE_FAILURE)
            # Sent in the same loop pass as the data store's action ran, so whatever the action
            # schedules with call_soon runs after the master has its answer.
            response.transaction_id, response.dev_id = tid, uid
            try:
                self.pdu_send(response, None)
            except Exception:  # noqa: BLE001 — the stream is lost: never leave the master waiting
                log.exception("Modbus/TCP: answer to transaction %d for %s could not be sent",
                              tid, self.peer())
                self.close()
                return
            self._unanswered -= 1  # answered: a read after it may be answered at once

    async def _execute(self, request: ModbusPDU, uid: int) -> ModbusPDU:
        context = self.server.context
        if isinstance(request, ReadWriteMultipleRegistersRequest):
            # pymodbus writes, then finds the read range illegal: check the read range first,
            # so that a request answered with an exception has changed nothing.
            probe = await context.async_getValues(
                uid, request.function_code, request.read_address, request.read_count)
            if isinstance(probe, ExcCodes):
                return ExceptionResponse(request.function_code, probe)
        return await request.datastore_update(context, uid)

    # ------------------------------------------------------------------ end

    def close(self, reconnect: bool = False) -> None:
        self._ending = True
        self._cancel_frame_timer()
        self._stop_worker()
        super().close(reconnect)

    def callback_disconnected(self, exc: Exception | None) -> None:
        self._ending = True
        self._cancel_frame_timer()
        self._stop_worker()
        super().callback_disconnected(exc)

    def _stop_worker(self) -> None:
        worker, self._worker = self._worker, None
        if worker is None or worker.done():
            return
        with contextlib.suppress(RuntimeError):  # no running loop: nothing can be current
            if worker is asyncio.current_task():
                return
        worker.cancel()
