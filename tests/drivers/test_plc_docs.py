"""docs/plc-interface.md is a contract: its tables and worked example must match the code."""

# ruff: noqa: F811 — the `plc` fixture comes from plc_peers
from __future__ import annotations

import re
from pathlib import Path

import pytest
from plc_peers import ArithmeticHandler, ServerFactory, cfg, plc  # noqa: F401

from drivers.links.base import LinkOutcome, LinkRequest
from drivers.links.modbus import (
    Command,
    Control,
    ErrorCode,
    State,
    Status,
    WordOrder,
)
from mvpose_core.reasons import Reason

DOC = (Path(__file__).resolve().parents[2] / "docs" / "plc-interface.md").read_text()


def _rows(first: str, second: str) -> bool:
    return re.search(rf"^\| {re.escape(first)} \| {re.escape(second)} \|", DOC, re.M) is not None


def test_bit_and_code_tables_match_the_enums() -> None:
    for flag in (*Control, *Status):
        assert _rows(str(flag.value.bit_length() - 1), str(flag.name)), flag
    for state in State:
        camel = "".join(w.capitalize() for w in state.name.split("_"))
        assert _rows(str(state.value), camel), state
    for code in Reason:
        if code:
            assert re.search(rf"^\| {code.value} \| {code.name}", DOC, re.M), code
    for err in ErrorCode:
        if err:
            assert _rows(str(err.value), err.name), err
    for cmd in Command:
        assert _rows(str(cmd.value), cmd.name), cmd


class ExampleHandler(ArithmeticHandler):
    """The station's answer used in the worked example (the first record of a store)."""

    async def measure(self, request: LinkRequest) -> LinkOutcome:
        return LinkOutcome(0, 1, (0.512, -1.25, 2.0, 0.05, -0.1, 0.25), 0.08, 0.012, 23.4)


def _dump(order: WordOrder) -> list[str]:
    block = DOC.split(f"<!-- worked-example:{order.name} -->", 1)[1].split("```")[1]
    return " ".join(line.split(":", 1)[1] for line in block.strip().splitlines()).split()


@pytest.mark.parametrize("order", [WordOrder.ABCD, WordOrder.CDAB])
async def test_worked_example_matches_the_server(plc: ServerFactory, order: WordOrder) -> None:
    _, twin = await plc(ExampleHandler(), cfg(word_order=order))
    await twin.write_trigger(1001)
    status = await twin.wait_for(lambda s: s.has(Status.RESULT_VALID), what="result")
    got = [f"{v:04X}" for v in status.regs]
    want = _dump(order)
    assert len(want) == 50 and len(got) == 84
    assert got[50:] == ["0000"] * 34  # the verify and hand-eye blocks: neither ran yet
    got = got[:50]
    assert want[1] == "hhhh"
    assert got[:1] + got[2:] == want[:1] + want[2:]
