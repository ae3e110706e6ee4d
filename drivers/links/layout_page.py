"""docs/fieldbus-layout.md, written from the layout's tables (drivers/links/layout.py).

    python -m drivers.links.layout_page > docs/fieldbus-layout.md

A test keeps the page equal to this output, so the page cannot drift from the code.
"""

from __future__ import annotations

from . import layout

_INTRO = """\
# The fieldbus layout

Every cyclic link carries the same two blocks of bytes: Modbus/TCP as registers
(docs/modbus.md), EtherNet/IP as assemblies (docs/ethernet-ip.md), S7 as two data blocks
(docs/s7.md), PROFINET as submodules (docs/profinet.md). The handshake over them is
docs/plc-interface.md. This page is written from `drivers/links/layout.py` by
`python -m drivers.links.layout_page`; a test keeps it current.

- **Output block** ({out} bytes): the PLC's outputs, written by the PLC, read by mvpose.
- **Input block** ({inp} bytes): the PLC's inputs, written by mvpose, read by the PLC.
- Offsets are bytes from the start of the block; word *n* of the Modbus map is bytes 2*n*, 2*n*+1.
- Types are IEC 61131-3: WORD (16 bits), UINT (16-bit unsigned), UDINT (32-bit unsigned), DINT
  (32-bit signed), REAL (IEEE 754 single), CHAR (one byte of ASCII).
- **Byte order**: S7 and PROFINET are big-endian; EtherNet/IP is little-endian (CIP); Modbus
  registers are big-endian words, and 32-bit values follow the link's `word_order` (ABCD: high
  word first; CDAB: low word first). Text is a byte string in every order. The input block's
  `test_real` ({tf}) and `test_dint` ({ti}) let a PLC program check its decoding once.
- **Fixed point and REAL**: poses travel as DINT fixed point (lengths in µm; Euler angles in
  1e-4 deg; quaternion components and radians in 1e-6), as SICK's layout does, and the offset
  also as REAL. A REAL keeps 24 bits of mantissa: 0.06 µm at 1000 mm, 0.03 µm at 300 mm, so
  the REAL offset is as precise as the measurement.
- The bits of `control` and `status`, the states, commands and codes are explained in
  docs/plc-interface.md; the timing of the handshake is the same on every bus.
"""


def _table(block: layout.Block) -> list[str]:
    rows = ["| byte | type | name | unit | meaning |", "|---:|---|---|---|---|"]
    for f in block.fields:
        kind = f.type if f.count == 1 else f"{f.type}[{f.count}]"
        span = f"{f.offset}" if f.size <= 2 else f"{f.offset}..{f.offset + f.size - 1}"
        rows.append(f"| {span} | {kind} | `{f.name}` | {f.unit} | {f.description} |")
    return rows


def render() -> str:
    """The page's Markdown."""
    lines = [_INTRO.format(out=layout.OUTPUT_SIZE, inp=layout.INPUT_SIZE,
                           tf=layout.TEST_FLOAT, ti=layout.TEST_INT)]
    lines += ["## Output block (PLC → mvpose)", "", *_table(layout.OUTPUT), ""]
    lines += ["## Input block (mvpose → PLC)", "", *_table(layout.INPUT), ""]
    return "\n".join(lines)


if __name__ == "__main__":
    print(render(), end="")
