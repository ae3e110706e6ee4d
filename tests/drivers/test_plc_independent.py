"""The PLC link driven by a second, independent Modbus implementation (pyModbusTCP).

pyModbusTCP has its own framing and its own word/float helpers, so an encoding mistake shared by
the server and the pymodbus-based twin cannot hide here.
"""

# ruff: noqa: F811 — the `plc` fixture comes from plc_peers
from __future__ import annotations

import asyncio
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import pytest
from plc_peers import ServerFactory, cfg, expected_outcome, plc, published_offset  # noqa: F401
from pyModbusTCP import utils
from pyModbusTCP.client import ModbusClient

from drivers.links import layout as r
from drivers.links.modbus import Control, WordOrder
from drivers.links.modbus.server import HR_MIRROR

READY, TRIGGER_ACK, RESULT_VALID, RESULT_OK, DONE_TOGGLE = 1, 2, 8, 16, 512
EN, TRIG, ACK = 16, 1, 2


@dataclass
class Seen:
    trigger_id: int
    result_id: int
    result_code: int
    ok: bool
    offset_counts: list[int]
    offset_float: list[float]


class LadderProgram:
    """What a PLC programmer writes from docs/plc-interface.md, on pyModbusTCP (blocking)."""

    def __init__(self, port: int, big_endian: bool) -> None:
        self.c = ModbusClient(host="127.0.0.1", port=port, auto_open=True, timeout=2.0)
        self.big = big_endian
        self.beat = 0

    def close(self) -> None:
        self.c.close()

    def i32(self, regs: list[int], at: int) -> int:
        return int(utils.get_2comp(utils.word_list_to_long(regs[at : at + 2], self.big)[0], 32))

    def u32(self, regs: list[int], at: int) -> int:
        return int(utils.word_list_to_long(regs[at : at + 2], self.big)[0])

    def f32(self, regs: list[int], at: int) -> float:
        return float(utils.decode_ieee(utils.word_list_to_long(regs[at : at + 2], self.big)[0]))

    def read(self) -> list[int]:
        regs = self.c.read_input_registers(0, r.IR_COUNT)
        assert regs is not None, f"read failed: {self.c.last_error_as_txt}"
        return list(regs)

    def control(self, bits: int, extra: list[int] | None = None) -> None:
        self.beat = (self.beat + 1) & 0xFFFF
        assert self.c.write_multiple_registers(0, [bits, self.beat, *(extra or [])])

    def poll(self, cond, timeout: float = 3.0) -> list[int]:
        deadline = time.monotonic() + timeout
        while True:
            regs = self.read()
            if cond(regs):
                return regs
            assert time.monotonic() < deadline, f"condition not met, status {regs[0]:#06x}"

    def run(self, trigger_id: int) -> Seen:
        regs = self.poll(lambda g: g[0] & READY)
        toggle = regs[0] & DONE_TOGGLE
        ids = utils.long_list_to_word([trigger_id], self.big)
        self.control(EN | TRIG, [0, 0, *ids, 0])
        regs = self.poll(lambda g: (g[0] & DONE_TOGGLE) != toggle)
        self.control(EN | ACK)
        self.poll(lambda g: not g[0] & (RESULT_VALID | TRIGGER_ACK) and g[0] & READY)
        return Seen(
            trigger_id=self.u32(regs, r.IR_TRIGGER_ID),
            result_id=self.u32(regs, r.IR_RESULT_ID),
            result_code=regs[r.IR_RESULT_CODE],
            ok=bool(regs[0] & RESULT_OK),
            offset_counts=[self.i32(regs, r.IR_OFFSET_INT + 2 * i) for i in range(6)],
            offset_float=[self.f32(regs, r.IR_OFFSET_FLOAT + 2 * i) for i in range(6)],
        )


@pytest.mark.parametrize("order", [WordOrder.ABCD, WordOrder.CDAB])
async def test_handshake_with_pymodbustcp(plc: ServerFactory, order: WordOrder) -> None:
    server, _ = await plc(config=cfg(word_order=order), connect=False)
    prog = LadderProgram(server.port, big_endian=order is WordOrder.ABCD)
    loop = asyncio.get_running_loop()
    ids = [3, 13, 70000, 0x8000_0001]
    try:
        with ThreadPoolExecutor(1) as pool:

            def program() -> tuple[list[int], list[Seen]]:
                first = prog.read()
                prog.control(EN)
                return first, [prog.run(t) for t in ids]

            first, seen = await loop.run_in_executor(pool, program)
    finally:
        prog.close()
    assert prog.f32(first, r.IR_TEST_FLOAT) == pytest.approx(123.45, abs=1e-5)
    assert prog.i32(first, r.IR_TEST_INT) == r.TEST_INT
    assert first[r.IR_WORD_ORDER] == int(order)
    for n, (tid, got) in enumerate(zip(ids, seen, strict=True), start=1):
        want = expected_outcome(tid)
        assert (got.trigger_id, got.result_id, got.result_code) == (tid, n, want.result_code)
        assert got.ok == (want.result_code == 0)
        scales = (1e3, 1e3, 1e3, 1e4, 1e4, 1e4)  # µm and 1e-4 deg, as documented
        sent = published_offset(tid)
        assert got.offset_counts == [round(v * s) for v, s in zip(sent, scales, strict=True)]
        assert got.offset_float == pytest.approx(list(sent), rel=1e-6, abs=1e-5)


async def test_exception_codes_seen_by_pymodbustcp(plc: ServerFactory) -> None:
    server, _ = await plc(connect=False)
    prog = LadderProgram(server.port, big_endian=True)
    loop = asyncio.get_running_loop()
    try:
        with ThreadPoolExecutor(1) as pool:

            def program() -> list[tuple[bool, int]]:
                c = prog.c
                out = [
                    (c.write_single_register(r.HR_WRITABLE_COUNT, 1), c.last_except),
                    (c.write_single_register(HR_MIRROR + 3, 1), c.last_except),
                    (c.write_single_register(r.HR_CONTROL, 0x0100 | EN), c.last_except),
                    (c.read_coils(0, 1) is not None, c.last_except),
                    (c.write_single_register(r.HR_CONTROL, int(Control.TRIGGER_ENABLE)), 0),
                ]
                return out

            results = await loop.run_in_executor(pool, program)
    finally:
        prog.close()
    assert results == [(False, 2), (False, 2), (False, 3), (False, 1), (True, 0)]
