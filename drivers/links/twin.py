"""The PLC twin: the PLC program's side of the handshake, over any bus that carries the layout.

:class:`PlcTwin` runs the handshake the way a PLC program does (heartbeat, enable, trigger →
answer → acknowledge, commands, error reset) on a :class:`PlcPort`: the bus's client (Modbus:
``modbus/twin.py``, and one per further backend) that reads the input block and writes the
output block as bytes. It decodes values with ``struct`` on the layout's word addresses, not
with the handshake's codecs, so that a word-order or scaling mistake in the device cannot cancel
itself out in tests.
"""

from __future__ import annotations

import asyncio
import contextlib
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from ..errors import DriverOperationError
from . import layout as r
from .layout import INPUT, OUTPUT, ByteOrder, Control, State, Status, VerifyVerdict, WordOrder


class PlcTwinError(DriverOperationError):
    """The twin saw something a PLC program would stop on (timeout, exception response)."""


class PlcPort(Protocol):
    """A bus client of the twin: the PLC's view of the two blocks."""

    byte_order: ByteOrder  # how the bus lays words into bytes
    word_order: WordOrder  # how the device orders the words of 32-bit values

    async def connect(self) -> None: ...

    async def read_inputs(self) -> bytes:
        """The whole input block (``layout.INPUT_SIZE`` bytes)."""
        ...

    async def write_outputs(self, offset: int, data: bytes) -> None:
        """Write ``data`` at byte ``offset`` of the output block, in one bus transaction."""
        ...

    def close(self) -> None: ...

    def abort(self) -> None:
        """Drop the connection without a goodbye, like a pulled cable or a PLC stop."""
        ...


def _raw32(words: Sequence[int], order: WordOrder) -> bytes:
    hi, lo = (words[0], words[1]) if order is WordOrder.ABCD else (words[1], words[0])
    return struct.pack(">HH", hi, lo)


@dataclass(frozen=True)
class PlcStatus:
    """The input block's words as the PLC reads them, decoded."""

    regs: tuple[int, ...]
    word_order: WordOrder

    def _conv(self, address: int, fmt: str) -> float | int:
        """The 32-bit value at word ``address``: ``fmt`` is struct's I, i or f."""
        value = struct.unpack(">" + fmt, _raw32(self.regs[address : address + 2],
                                                self.word_order))[0]
        assert isinstance(value, int | float)
        return value

    @property
    def status(self) -> Status:
        return Status(self.regs[r.IR_STATUS])

    def has(self, flag: Status) -> bool:
        return bool(self.regs[r.IR_STATUS] & flag)

    @property
    def state(self) -> State:
        return State(self.regs[r.IR_STATE])

    @property
    def heartbeat(self) -> int:
        return self.regs[r.IR_HEARTBEAT]

    @property
    def error_code(self) -> int:
        return self.regs[r.IR_ERROR_CODE]

    @property
    def recipe(self) -> int:
        return self.regs[r.IR_RECIPE]

    @property
    def command_result(self) -> int:
        return self.regs[r.IR_COMMAND_RESULT]

    @property
    def trigger_id(self) -> int:
        return int(self._conv(r.IR_TRIGGER_ID, "I"))

    @property
    def result_id(self) -> int:
        return int(self._conv(r.IR_RESULT_ID, "I"))

    @property
    def result_code(self) -> int:
        return self.regs[r.IR_RESULT_CODE]

    @property
    def processing_ms(self) -> float:
        return self.regs[r.IR_PROCESSING_TIME] / 10.0

    @property
    def views_done(self) -> int:
        return self.regs[r.IR_VIEWS_DONE]

    @property
    def offset_counts(self) -> tuple[int, ...]:
        """The 6 raw int32 counts (µm, 1e-4 deg, ... see the register map)."""
        return tuple(int(self._conv(r.IR_OFFSET_INT + 2 * i, "i")) for i in range(6))

    @property
    def offset_float(self) -> tuple[float, ...]:
        return tuple(float(self._conv(r.IR_OFFSET_FLOAT + 2 * i, "f")) for i in range(6))

    @property
    def sigma_counts(self) -> tuple[int, int]:
        """1σ translation (µm) and rotation (1e-4 deg)."""
        return int(self._conv(r.IR_SIGMA_TRANS, "i")), int(
            self._conv(r.IR_SIGMA_ROT, "i")
        )

    @property
    def convention_code(self) -> int:
        return self.regs[r.IR_CONVENTION]

    @property
    def test_float(self) -> float:
        return float(self._conv(r.IR_TEST_FLOAT, "f"))

    @property
    def test_int(self) -> int:
        return int(self._conv(r.IR_TEST_INT, "i"))

    @property
    def verify_result_id(self) -> int:
        return int(self._conv(r.IR_VERIFY_RESULT_ID, "I"))

    @property
    def verify_verdict(self) -> VerifyVerdict:
        return VerifyVerdict(self.regs[r.IR_VERIFY_VERDICT])

    @property
    def verify_difference(self) -> tuple[float, ...]:
        """The last verify's 6-DoF difference to the taught pose (PLC form, float32)."""
        return tuple(float(self._conv(r.IR_VERIFY_DIFFERENCE + 2 * i, "f"))
                     for i in range(6))

    @property
    def verify_displacement_mm(self) -> float:
        return float(self._conv(r.IR_VERIFY_DISPLACEMENT, "f"))

    @property
    def verify_rotation_deg(self) -> float:
        return float(self._conv(r.IR_VERIFY_ROTATION, "f"))

    @property
    def handeye_poses(self) -> int:
        return self.regs[r.IR_HANDEYE_POSES]

    @property
    def handeye_pose(self) -> int:
        return self.regs[r.IR_HANDEYE_POSE]

    @property
    def handeye_version(self) -> int:
        return int(self._conv(r.IR_HANDEYE_VERSION, "I"))

    @property
    def handeye_figures(self) -> tuple[float, ...]:
        """1σ mm and deg, hold-out RMS px, hold-out mm and deg of the last calculate."""
        return tuple(float(self._conv(a, "f")) for a in (
            r.IR_HANDEYE_SIGMA_TRANS, r.IR_HANDEYE_SIGMA_ROT, r.IR_HANDEYE_HOLDOUT_PX,
            r.IR_HANDEYE_HOLDOUT_MM, r.IR_HANDEYE_HOLDOUT_DEG))


class PlcTwin:
    """A PLC program on a :class:`PlcPort`. Every wait polls the device with a deadline."""

    def __init__(self, port: PlcPort, *, poll_s: float = 0.0) -> None:
        self.port = port
        self.word_order = port.word_order
        self.poll_s = poll_s
        self.control = Control(0)
        self.heartbeat = 0
        self._beating = False
        self._beat_stop: asyncio.Event | None = None
        #: seconds from writing the last cycle's TRIGGER to reading its answer (RESULT_VALID or
        #: VIEW_DONE): the PLC's view of the latency, without the READY check before it and the
        #: RESULT_ACK handshake after it
        self.last_answer_s = float("nan")

    async def connect(self) -> PlcTwin:
        await self.port.connect()
        return self

    def close(self) -> None:
        self.port.close()

    def abort(self) -> None:
        """Drop the connection without a goodbye, like a pulled cable or a PLC stop."""
        self.port.abort()

    async def __aenter__(self) -> PlcTwin:
        return await self.connect()

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ block access

    def _regs32(self, value: int | float, fmt: str) -> list[int]:
        hi, lo = struct.unpack(">HH", struct.pack(">" + fmt, value))
        return [hi, lo] if self.word_order is WordOrder.ABCD else [lo, hi]

    async def read_status(self) -> PlcStatus:
        data = await self.port.read_inputs()
        words = INPUT.to_words(data, self.port.byte_order)
        return PlcStatus(tuple(words), self.word_order)

    async def write(self, address: int, values: Sequence[int]) -> None:
        """Write words at word ``address`` of the output block, in one transaction."""
        data = OUTPUT.to_bytes(list(values), self.port.byte_order, start=address)
        await self.port.write_outputs(2 * address, data)

    async def set_control(self, control: Control, *, beat: bool = True) -> None:
        """Write the control word together with the next heartbeat (registers 0-1)."""
        self.control = Control(control)
        if beat:
            self.heartbeat = (self.heartbeat + 1) & 0xFFFF
        await self.write(r.HR_CONTROL, [int(self.control), self.heartbeat])

    async def beat(self) -> None:
        await self.set_control(self.control)

    async def keep_alive(self, period_s: float = 0.1) -> None:
        """Change the heartbeat every ``period_s`` until :meth:`stop_keep_alive`, as the PLC's
        cyclic task does; run it as a task next to the handshake (pymodbus serialises the
        client's requests)."""
        self._beating = True
        self._beat_stop = asyncio.Event()
        while self._beating:
            await self.beat()
            with contextlib.suppress(TimeoutError):  # a stop ends the wait, not the write
                async with asyncio.timeout(period_s):
                    await self._beat_stop.wait()

    def stop_keep_alive(self) -> None:
        """End :meth:`keep_alive` at its next cycle. Cancelling its task alone is not enough on
        Python 3.11: ``asyncio.wait_for`` (pymodbus awaits every response with it) drops a
        cancellation that arrives in the same loop pass as the response (CPython gh-86296),
        and the heartbeat would then run for ever. A heartbeat write in flight is finished
        first, so a twin that then disconnects leaves no request unanswered."""
        self._beating = False
        if self._beat_stop is not None:
            self._beat_stop.set()

    async def wait_for(
        self, predicate: Callable[[PlcStatus], bool], timeout: float = 2.0, what: str = "condition"
    ) -> PlcStatus:
        deadline = time.monotonic() + timeout
        while True:
            status = await self.read_status()
            if predicate(status):
                return status
            if time.monotonic() > deadline:
                raise PlcTwinError(
                    f"PLC twin: no {what} within {timeout} s (state {status.state.name}, "
                    f"status {status.status!r}, error {status.error_code})"
                )
            await asyncio.sleep(self.poll_s)

    # ------------------------------------------------------------------ PLC program steps

    async def enable(self, on: bool = True) -> PlcStatus:
        ctl = (
            self.control | Control.TRIGGER_ENABLE if on else self.control & ~Control.TRIGGER_ENABLE
        )
        await self.set_control(ctl)
        return await self.read_status()

    async def write_trigger(
        self,
        trigger_id: int,
        view_index: int = 0,
        pose_counts: Sequence[int] | None = None,
        part_id: str | None = None,
    ) -> None:
        """Write the trigger data and raise TRIGGER in one request (control word first)."""
        ctl = (self.control | Control.TRIGGER | Control.TRIGGER_ENABLE) & ~Control.RESULT_ACK
        ctl = (
            ctl | Control.ROBOT_POSE_VALID
            if pose_counts is not None
            else ctl & ~Control.ROBOT_POSE_VALID
        )
        self.control = ctl
        self.heartbeat = (self.heartbeat + 1) & 0xFFFF
        regs = [
            int(ctl),
            self.heartbeat,
            0,
            0,
            *self._regs32(trigger_id, "I"),
            view_index,
            0,
        ]
        if pose_counts is not None or part_id is not None:
            for count in pose_counts if pose_counts is not None else (0,) * 6:
                regs += self._regs32(int(count), "i")
            text = (part_id or "").encode("ascii").ljust(r.PART_ID_CHARS, b"\0")
            regs += [text[i] << 8 | text[i + 1] for i in range(0, r.PART_ID_CHARS, 2)]
        await self.write(r.HR_CONTROL, regs)

    async def cycle(
        self,
        trigger_id: int,
        view_index: int = 0,
        pose_counts: Sequence[int] | None = None,
        part_id: str | None = None,
        timeout: float = 2.0,
    ) -> PlcStatus:
        """One trigger → answer handshake; returns the status holding the answer (result or view).

        READY → write data + TRIGGER → wait until the answer carries our trigger id → drop
        TRIGGER and raise RESULT_ACK together → wait until RESULT_VALID/VIEW_DONE clear and READY.
        """
        await self.wait_for(lambda s: s.has(Status.READY), timeout, "READY")
        before = await self.read_status()
        toggle = before.has(Status.DONE_TOGGLE)
        missed = before.has(Status.MISSED_TRIGGER)
        t_trigger = time.perf_counter()
        await self.write_trigger(trigger_id, view_index, pose_counts, part_id)
        answer = await self.wait_for(
            lambda s: (
                s.has(Status.DONE_TOGGLE) != toggle or (s.has(Status.MISSED_TRIGGER) > missed)
            ),
            timeout,
            f"answer to trigger {trigger_id}",
        )
        self.last_answer_s = time.perf_counter() - t_trigger
        if answer.has(Status.DONE_TOGGLE) == toggle:
            raise PlcTwinError(f"PLC twin: trigger {trigger_id} was missed")
        if answer.trigger_id != trigger_id:
            raise PlcTwinError(
                f"PLC twin: answer echoes trigger {answer.trigger_id}, not {trigger_id}"
            )
        await self.set_control((self.control & ~Control.TRIGGER) | Control.RESULT_ACK)
        await self.wait_for(
            lambda s: not s.has(Status.RESULT_VALID | Status.VIEW_DONE | Status.TRIGGER_ACK),
            timeout,
            "acknowledgement",
        )
        return answer

    async def command(self, code: int, argument: int = 0, timeout: float = 5.0) -> PlcStatus:
        """Run a command; returns the status with COMMAND_DONE or COMMAND_FAILED set."""
        await self.write(r.HR_COMMAND, [code, argument])
        await self.set_control(self.control | Control.EXECUTE_COMMAND)
        done = await self.wait_for(
            lambda s: s.has(Status.COMMAND_DONE | Status.COMMAND_FAILED), timeout, "command end"
        )
        await self.set_control(self.control & ~Control.EXECUTE_COMMAND)
        await self.wait_for(
            lambda s: not s.has(Status.COMMAND_DONE | Status.COMMAND_FAILED),
            timeout,
            "command clear",
        )
        return done

    async def command_with_pose(self, code: int, pose_counts: Sequence[int],
                                timeout: float = 5.0) -> PlcStatus:
        """Run a command that takes the robot pose (HANDEYE_ADD_POSE): the pose registers with
        ROBOT_POSE_VALID, as a trigger sends them, then the command."""
        regs: list[int] = []
        for count in pose_counts:
            regs += self._regs32(int(count), "i")
        await self.write(r.HR_ROBOT_POSE, regs)
        await self.set_control(self.control | Control.ROBOT_POSE_VALID)
        try:
            return await self.command(code, 0, timeout)
        finally:
            await self.set_control(self.control & ~Control.ROBOT_POSE_VALID)

    async def reset_error(self, timeout: float = 2.0) -> PlcStatus:
        await self.set_control(self.control & ~Control.ERROR_RESET)
        await self.set_control(self.control | Control.ERROR_RESET)
        status = await self.wait_for(lambda s: not s.has(Status.ERROR), timeout, "error cleared")
        await self.set_control(self.control & ~Control.ERROR_RESET)
        return status
