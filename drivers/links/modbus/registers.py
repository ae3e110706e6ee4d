"""The PLC register map as data: addresses, bit meanings, state, command, result and error codes.

This module is the contract with the PLC program (docs/plc-interface.md documents it). Addresses
are 0-based protocol addresses. Once released, change nothing here except by adding at the end.
"""

from __future__ import annotations

from enum import IntEnum, IntFlag
from typing import Final

# --------------------------------------------------------------------------- holding (PLC → server)

#: Holding registers 0..39 are written by the PLC.
HR_CONTROL: Final = 0
HR_HEARTBEAT: Final = 1
HR_COMMAND: Final = 2
HR_COMMAND_ARG: Final = 3
HR_TRIGGER_ID: Final = 4  # u32, 2 registers
HR_VIEW_INDEX: Final = 6
HR_RESERVED_7: Final = 7
HR_ROBOT_POSE: Final = 8  # 6 × int32, 12 registers
HR_PART_ID: Final = 20  # 40 ASCII characters, 20 registers
PART_ID_CHARS: Final = 40
HR_WRITABLE_COUNT: Final = 40

#: Holding registers 100..149 mirror the input registers 0..49 (read-only) for PLCs that cannot
#: read input registers (function code 4).
HR_MIRROR: Final = 100

# --------------------------------------------------------------------------- input (server → PLC)

IR_STATUS: Final = 0
IR_HEARTBEAT: Final = 1
IR_STATE: Final = 2
IR_ERROR_CODE: Final = 3
IR_RECIPE: Final = 4
IR_COMMAND_RESULT: Final = 5
IR_TRIGGER_ID: Final = 6  # u32 echo of the accepted trigger id
IR_RESULT_ID: Final = 8  # u32, 0 = no result yet
IR_RESULT_CODE: Final = 10
IR_PROCESSING_TIME: Final = 11  # 0.1 ms, saturates at 65535
IR_VIEWS_DONE: Final = 12
IR_OFFSET_INT: Final = 16  # 6 × int32
IR_OFFSET_FLOAT: Final = 28  # 6 × float32
IR_SIGMA_TRANS: Final = 40  # int32 µm
IR_SIGMA_ROT: Final = 42  # int32 1e-4 deg
IR_CONVENTION: Final = 44
IR_WORD_ORDER: Final = 45  # 0 = ABCD, 1 = CDAB
IR_TEST_FLOAT: Final = 46  # float32 123.45
IR_TEST_INT: Final = 48  # int32 123456789
# the last calibration verify (command VERIFY), published before its COMMAND_DONE
IR_VERIFY_RESULT_ID: Final = 50  # u32, the verify record's result id
IR_VERIFY_VERDICT: Final = 52  # VerifyVerdict
IR_VERIFY_RESERVED_53: Final = 53
IR_VERIFY_DIFFERENCE: Final = 54  # 6 × float32: the difference to the taught pose (PLC form)
IR_VERIFY_DISPLACEMENT: Final = 66  # float32 mm at the grasp point
IR_VERIFY_ROTATION: Final = 68  # float32 deg
IR_COUNT: Final = 70

TEST_FLOAT: Final = 123.45
TEST_INT: Final = 123456789


class Control(IntFlag):
    """Bits of holding register 0, written by the PLC."""

    TRIGGER = 1 << 0  # rising edge starts a measurement
    RESULT_ACK = 1 << 1  # rising edge acknowledges RESULT_VALID / VIEW_DONE
    ERROR_RESET = 1 << 2  # rising edge leaves Error once its cause is gone
    EXECUTE_COMMAND = 1 << 3  # rising edge runs the command in registers 2-3
    TRIGGER_ENABLE = 1 << 4  # level: 0 halts the station (state Halted)
    ROBOT_POSE_VALID = 1 << 5  # level, sampled at the trigger edge: registers 8-19 hold a pose


CONTROL_DEFINED: Final = int(
    Control.TRIGGER
    | Control.RESULT_ACK
    | Control.ERROR_RESET
    | Control.EXECUTE_COMMAND
    | Control.TRIGGER_ENABLE
    | Control.ROBOT_POSE_VALID
)


class Status(IntFlag):
    """Bits of input register 0, written by the server."""

    READY = 1 << 0
    TRIGGER_ACK = 1 << 1
    BUSY = 1 << 2
    RESULT_VALID = 1 << 3
    RESULT_OK = 1 << 4
    ERROR = 1 << 5
    COMMAND_BUSY = 1 << 6
    COMMAND_DONE = 1 << 7
    COMMAND_FAILED = 1 << 8
    DONE_TOGGLE = 1 << 9
    MISSED_TRIGGER = 1 << 10
    VIEW_DONE = 1 << 11
    ONLINE = 1 << 12


class State(IntEnum):
    """Station state, named as in OPC 40100 (Machine Vision); register 2."""

    PREOPERATIONAL = 1  # no PLC heartbeat seen yet
    HALTED = 2  # TRIGGER_ENABLE is 0
    INITIALIZED = 3  # no recipe selected (recipe 0)
    READY = 4  # a trigger will be accepted
    SINGLE_EXECUTION = 5  # a measurement is running
    ERROR = 6  # see the error code; needs ERROR_RESET


class Command(IntEnum):
    """Command codes (register 2), run on a rising edge of EXECUTE_COMMAND."""

    SELECT_RECIPE = 1  # argument: recipe number (1..65535)
    TEACH_REFERENCE = 2  # the next final result becomes the zero offset
    RESET = 3  # drop a half-done multi-view sequence
    VERIFY = 4  # measure the taught reference part and judge it (registers 50-69)


class VerifyVerdict(IntEnum):
    """Register 52: the last verify's verdict."""

    NONE = 0  # no verify yet, or the last one measured nothing to judge (see register 5)
    PASSED = 1  # the reference part is within the limits of its taught pose
    FAILED = 2  # it is not: the calibration or the cameras have moved


class ErrorCode(IntEnum):
    """Why the station is in state Error (register 3)."""

    NONE = 0
    WATCHDOG = 1  # the PLC heartbeat (register 1) stopped changing
    TRIGGER_HELD = 2  # TRIGGER stayed high longer than the hold limit after the answer
    INTERNAL = 3  # reset of the pipeline failed


class WordOrder(IntEnum):
    """Order of the two words of a 32-bit value (bytes inside a word are always big-endian)."""

    ABCD = 0  # high word first (Modicon, Siemens)
    CDAB = 1  # low word first (many Rockwell and Schneider configurations)
