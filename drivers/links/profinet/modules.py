"""The IO-device's modules and submodules, taken from the fieldbus layout
(:mod:`drivers.links.layout`): slot 0 the device access point (with its interface and port
submodules), slot 1 the handshake (PLC outputs up to the robot pose), slot 2 the robot pose
and part id (the rest of the PLC outputs), slot 3 the result (all PLC inputs). The GSDML and
the Connect check both read this table.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

from .. import layout

API: Final = 0


@dataclass(frozen=True)
class Submodule:
    """One plugged submodule: where, its ident numbers, and which bytes of the layout's blocks
    it carries (``output``: the PLC writes them; ``input``: the PLC reads them)."""

    name: str
    slot: int
    subslot: int
    module_ident: int
    submodule_ident: int
    output: tuple[int, int] = (0, 0)  # (offset, length) in layout.OUTPUT
    input: tuple[int, int] = (0, 0)  # (offset, length) in layout.INPUT

    @property
    def output_length(self) -> int:
        return self.output[1]

    @property
    def input_length(self) -> int:
        return self.input[1]


_POSE = 2 * layout.HR_ROBOT_POSE
DAP = Submodule("device access point", 0, 1, 0x00000001, 0x00000001)
INTERFACE = Submodule("interface", 0, 0x8000, 0x00000001, 0x00000002)
PORT = Submodule("port 1", 0, 0x8001, 0x00000001, 0x00000003)
HANDSHAKE = Submodule("handshake", 1, 1, 0x00000010, 0x00000011, output=(0, _POSE))
ROBOT_POSE = Submodule("robot pose", 2, 1, 0x00000020, 0x00000021,
                       output=(_POSE, layout.OUTPUT_SIZE - _POSE))
RESULT = Submodule("result", 3, 1, 0x00000030, 0x00000031, input=(0, layout.INPUT_SIZE))
SUBMODULES: Final = (DAP, INTERFACE, PORT, HANDSHAKE, ROBOT_POSE, RESULT)


def find(slot: int, subslot: int) -> Submodule | None:
    return next((s for s in SUBMODULES if s.slot == slot and s.subslot == subslot), None)


def output_fields(sub: Submodule) -> list[layout.Field]:
    lo, n = sub.output
    return [f for f in layout.OUTPUT_FIELDS if lo <= f.offset < lo + n]


def input_fields(sub: Submodule) -> list[layout.Field]:
    lo, n = sub.input
    return [f for f in layout.INPUT_FIELDS if lo <= f.offset < lo + n]
