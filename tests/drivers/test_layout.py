"""The fieldbus layout: its tables, its byte orders, and the handshake carried as bytes.

The PLC twin drives a handshake runner through an in-memory port that hands the runner whole
output images and reads whole input images, as a cyclic bus does; with BIG and LITTLE byte
order the twin decodes the same answers."""

from __future__ import annotations

import struct

import pytest

from drivers.links import layout
from drivers.links.handshake import HandshakeConfig, HandshakeRunner
from drivers.links.layout import INPUT, OUTPUT, ByteOrder, Status
from drivers.links.twin import PlcTwin
from tests.drivers.plc_peers import ArithmeticHandler, published_offset


@pytest.mark.parametrize("block", [OUTPUT, INPUT], ids=["output", "input"])
def test_fields_tile_the_block_without_gaps(block: layout.Block) -> None:
    end = 0
    for f in block.fields:
        assert f.offset == end, f"{f.name} starts at {f.offset}, the previous field ends at {end}"
        end = f.offset + f.size
    assert end == block.size
    assert len({f.name for f in block.fields}) == len(block.fields)


def test_sizes_are_the_modbus_map_in_bytes() -> None:
    want = (2 * layout.HR_WRITABLE_COUNT, 2 * layout.IR_COUNT)
    assert (OUTPUT.size, INPUT.size) == want == (80, 168)


def test_little_endian_values_and_text_in_order() -> None:
    words = [0] * (OUTPUT.size // 2)
    tid = layout.HR_TRIGGER_ID
    words[tid : tid + 2] = [0x0001, 0xE240]  # CDAB: 0xE2400001
    words[layout.HR_PART_ID] = ord("V") << 8 | ord("W")
    data = OUTPUT.to_bytes(words, ByteOrder.LITTLE)
    off = layout.HR_TRIGGER_ID * 2
    assert struct.unpack_from("<I", data, off)[0] == 0xE2400001
    assert data[layout.HR_PART_ID * 2 : layout.HR_PART_ID * 2 + 2] == b"VW"
    assert OUTPUT.to_words(data, ByteOrder.LITTLE) == words
    assert OUTPUT.to_words(OUTPUT.to_bytes(words, ByteOrder.BIG), ByteOrder.BIG) == words


def test_a_slice_must_fit_its_block() -> None:
    with pytest.raises(ValueError, match="do not fit the input block"):
        INPUT.to_words(b"\0" * 4, ByteOrder.BIG, start=INPUT.size // 2 - 1)
    with pytest.raises(ValueError, match="do not fit"):
        OUTPUT.to_bytes([1], ByteOrder.LITTLE, start=-1)


class MemoryPort:
    """The twin's bus as a cyclic bus carries it: whole images, no registers."""

    def __init__(self, runner: HandshakeRunner, order: ByteOrder) -> None:
        self.runner = runner
        self.byte_order = order
        self.word_order = order.word_order
        self.outputs = bytearray(OUTPUT.size)

    async def connect(self) -> None:
        pass

    async def read_inputs(self) -> bytes:
        return self.runner.input_image(self.byte_order)

    async def write_outputs(self, offset: int, data: bytes) -> None:
        self.outputs[offset : offset + len(data)] = data
        self.runner.write_output(bytes(self.outputs), self.byte_order)

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass


@pytest.mark.parametrize("order", [ByteOrder.BIG, ByteOrder.LITTLE], ids=lambda o: o.value)
async def test_the_handshake_over_whole_images(order: ByteOrder) -> None:
    handler = ArithmeticHandler()
    cfg = HandshakeConfig(word_order=order.word_order, initial_recipe=1, watchdog_s=10.0)
    runner = HandshakeRunner(handler, cfg, link="memory")
    await runner.start()
    try:
        twin = PlcTwin(MemoryPort(runner, order))
        await twin.connect()
        ready = await twin.enable()
        assert ready.test_float == pytest.approx(layout.TEST_FLOAT, abs=1e-4)
        assert ready.test_int == layout.TEST_INT
        for trigger_id in (70001, 70005):  # 70005 = 13 × 5385: a NOK of the arithmetic handler
            answer = await twin.cycle(trigger_id, part_id="WVWZZZ1KZ-ÄX".encode(
                "ascii", "replace").decode())
            assert answer.trigger_id == trigger_id
            assert answer.result_id == handler.seq
            assert answer.offset_float == pytest.approx(published_offset(trigger_id), abs=1e-4)
            assert answer.has(Status.RESULT_OK) == (trigger_id % 13 != 0)
        assert [r.part_id for r in handler.requests] == ["WVWZZZ1KZ-?X"] * 2
        assert {r.link for r in handler.requests} == {"memory"}
    finally:
        await runner.stop()


async def test_a_wrong_image_size_is_refused() -> None:
    runner = HandshakeRunner(ArithmeticHandler(), HandshakeConfig(watchdog_s=0))
    await runner.start()
    try:
        with pytest.raises(ValueError, match="output block is 80 bytes, got 79"):
            runner.write_output(b"\0" * 79, ByteOrder.BIG)
    finally:
        await runner.stop()


def test_the_layout_page_is_current() -> None:
    from pathlib import Path

    from drivers.links.layout_page import render

    page = Path(__file__).resolve().parents[2] / "docs" / "fieldbus-layout.md"
    assert page.read_text(encoding="utf-8") == render(), (
        "docs/fieldbus-layout.md is stale: python -m drivers.links.layout_page > "
        "docs/fieldbus-layout.md")
