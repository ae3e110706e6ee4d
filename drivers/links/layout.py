"""The fieldbus layout: the handshake and the result block, once, for every cyclic link.

This module is the contract with the PLC program (docs/fieldbus-layout.md lists it, generated
from the tables at the end; docs/plc-interface.md explains the handshake). Two blocks:

- the **output** block (PLC outputs, written by the PLC): ``OUTPUT_SIZE`` bytes;
- the **input** block (PLC inputs, written by mvpose): ``INPUT_SIZE`` bytes.

Addresses below are 16-bit word indices: word ``n`` is bytes ``2n, 2n+1`` of its block. Modbus
shows the output block as holding registers 0..39 and the input block as input registers 0..83;
EtherNet/IP as its output and input assemblies, S7 as two data blocks, PROFINET as submodules.
Every bus carries the same bytes; only the byte order differs (:class:`ByteOrder`). Once
released, change nothing here except by adding at the end.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum, IntEnum, IntFlag
from typing import Final, Literal

# --------------------------------------------------------------------------- holding (PLC → server)

#: Words 0..39 of the output block (Modbus: holding registers 0..39) are written by the PLC.
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
# the hand-eye session (commands HANDEYE_*), published before each step's COMMAND_DONE/FAILED
IR_HANDEYE_POSES: Final = 70  # poses the session holds
IR_HANDEYE_POSE: Final = 71  # the pose the last step was about (1-based; "not found in pose k")
IR_HANDEYE_VERSION: Final = 72  # u32, the stored calibration version waiting for activation
IR_HANDEYE_SIGMA_TRANS: Final = 74  # float32 mm, 1σ of the hand-eye translation
IR_HANDEYE_SIGMA_ROT: Final = 76  # float32 deg
IR_HANDEYE_HOLDOUT_PX: Final = 78  # float32 px, the held-out poses' reprojection RMS
IR_HANDEYE_HOLDOUT_MM: Final = 80  # float32 mm, largest held-out flange pose error
IR_HANDEYE_HOLDOUT_DEG: Final = 82  # float32 deg
IR_COUNT: Final = 84

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
    # the robot-driven hand-eye (docs/calibration.md): answers in register 5 (0 or the
    # session's code, 201-213) and registers 70-83
    HANDEYE_BEGIN = 5  # argument: poses held out to check the result (0: the default, 3)
    HANDEYE_ADD_POSE = 6  # the flange pose in registers 8-19 with ROBOT_POSE_VALID
    HANDEYE_CALCULATE = 7  # solve; the result is stored as a calibration version


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
    """Order of the two words of a 32-bit value (on Modbus the bytes inside a word are always
    big-endian; a cyclic bus fixes both through its :class:`ByteOrder`)."""

    ABCD = 0  # high word first (Modicon, Siemens)
    CDAB = 1  # low word first (many Rockwell and Schneider configurations)


# --------------------------------------------------------------------------- the blocks in bytes

#: bytes of the output block (PLC outputs: control, heartbeat, command, trigger, pose, part id)
OUTPUT_SIZE: Final = 2 * HR_WRITABLE_COUNT
#: bytes of the input block (PLC inputs: status, ids, result code, offset, 1σ, verify block,
#: hand-eye block)
INPUT_SIZE: Final = 2 * IR_COUNT


class ByteOrder(Enum):
    """How a bus lays the words of a block into bytes.

    ``BIG``: every value big-endian (S7, PROFINET, Modbus with ABCD). ``LITTLE``: every value
    little-endian (EtherNet/IP: CIP is little-endian). Text is a byte string in either order.
    """

    BIG = "big"
    LITTLE = "little"

    @property
    def word_order(self) -> WordOrder:
        """The word order of 32-bit values that makes them big- or little-endian in bytes."""
        return WordOrder.ABCD if self is ByteOrder.BIG else WordOrder.CDAB


FieldType = Literal["WORD", "UINT", "UDINT", "DINT", "REAL", "CHAR"]
_TYPE_BYTES: Final[dict[str, int]] = {
    "WORD": 2, "UINT": 2, "UDINT": 4, "DINT": 4, "REAL": 4, "CHAR": 1}


@dataclass(frozen=True)
class Field:
    """One field of a block: IEC 61131-3 type names, byte offset in its block."""

    name: str
    offset: int  # bytes from the start of the block
    type: FieldType
    count: int  # elements (a pose is 6 DINT, the part id 40 CHAR)
    unit: str
    description: str

    @property
    def size(self) -> int:
        return _TYPE_BYTES[self.type] * self.count


@dataclass(frozen=True)
class Block:
    """One direction's block: its fields, and the conversion between its bytes and the 16-bit
    words the handshake works on (word ``n`` = bytes ``2n, 2n+1``)."""

    name: str
    size: int
    fields: tuple[Field, ...]

    def _text_words(self) -> frozenset[int]:
        return frozenset(
            w for f in self.fields if f.type == "CHAR"
            for w in range(f.offset // 2, (f.offset + f.size) // 2))

    def to_words(self, data: bytes, order: ByteOrder, start: int = 0) -> list[int]:
        """Bytes of the block as words; ``data`` starts at word ``start`` (default: the whole
        block from its first byte)."""
        self._check(start, len(data))
        n = len(data) // 2
        big = list(struct.unpack(f">{n}H", data))
        if order is ByteOrder.BIG:
            return big
        text = self._text_words()
        little = struct.unpack(f"<{n}H", data)
        return [big[i] if start + i in text else little[i] for i in range(n)]

    def to_bytes(self, words: Sequence[int], order: ByteOrder, start: int = 0) -> bytes:
        """Inverse of :meth:`to_words`."""
        self._check(start, 2 * len(words))
        if order is ByteOrder.BIG:
            return struct.pack(f">{len(words)}H", *words)
        text = self._text_words()
        return b"".join(
            struct.pack(">H" if start + i in text else "<H", w) for i, w in enumerate(words))

    def _check(self, start: int, n_bytes: int) -> None:
        if n_bytes % 2 or start < 0 or 2 * start + n_bytes > self.size:
            raise ValueError(
                f"{n_bytes} bytes from word {start} do not fit the {self.name} block "
                f"({self.size} bytes)")


def _f(name: str, word: int, type_: FieldType, count: int, unit: str, text: str) -> Field:
    return Field(name, 2 * word, type_, count, unit, text)


OUTPUT_FIELDS: Final = (
    _f("control", HR_CONTROL, "WORD", 1, "bits",
       "TRIGGER, RESULT_ACK, ERROR_RESET, EXECUTE_COMMAND, TRIGGER_ENABLE, ROBOT_POSE_VALID"),
    _f("heartbeat", HR_HEARTBEAT, "UINT", 1, "", "changed by the PLC at least every watchdog"),
    _f("command", HR_COMMAND, "UINT", 1, "", "command code, run on EXECUTE_COMMAND's rising edge"),
    _f("command_argument", HR_COMMAND_ARG, "UINT", 1, "", "the command's argument"),
    _f("trigger_id", HR_TRIGGER_ID, "UDINT", 1, "", "the PLC's id of this trigger, echoed back"),
    _f("view_index", HR_VIEW_INDEX, "UINT", 1, "", "view of a multi-view sequence (0 = single)"),
    _f("reserved_7", HR_RESERVED_7, "WORD", 1, "", "0"),
    _f("robot_pose", HR_ROBOT_POSE, "DINT", 6, "µm; 1e-4 deg or 1e-6",
       "flange pose in the recipe's convention, fixed point (scaled as the offset)"),
    _f("part_id", HR_PART_ID, "CHAR", PART_ID_CHARS, "ASCII", "part id, NUL padded"),
)

INPUT_FIELDS: Final = (
    _f("status", IR_STATUS, "WORD", 1, "bits",
       "READY, TRIGGER_ACK, BUSY, RESULT_VALID, RESULT_OK, ERROR, COMMAND_BUSY, COMMAND_DONE, "
       "COMMAND_FAILED, DONE_TOGGLE, MISSED_TRIGGER, VIEW_DONE, ONLINE"),
    _f("heartbeat", IR_HEARTBEAT, "UINT", 1, "", "counts up every 50 ms"),
    _f("state", IR_STATE, "UINT", 1, "", "station state (OPC 40100 names)"),
    _f("error_code", IR_ERROR_CODE, "UINT", 1, "", "why the state is Error"),
    _f("recipe", IR_RECIPE, "UINT", 1, "", "selected recipe (0 = none)"),
    _f("command_result", IR_COMMAND_RESULT, "UINT", 1, "", "0 or the reason code of the command"),
    _f("trigger_id", IR_TRIGGER_ID, "UDINT", 1, "", "echo of the accepted trigger id"),
    _f("result_id", IR_RESULT_ID, "UDINT", 1, "", "durable id of the stored result (0 = none)"),
    _f("result_code", IR_RESULT_CODE, "UINT", 1, "", "0 = OK, else the reason code"),
    _f("processing_time", IR_PROCESSING_TIME, "UINT", 1, "0.1 ms", "trigger to result"),
    _f("views_done", IR_VIEWS_DONE, "UINT", 1, "", "views measured in this sequence"),
    _f("reserved_13", IR_VIEWS_DONE + 1, "WORD", 3, "", "0"),
    _f("offset", IR_OFFSET_INT, "DINT", 6, "µm; 1e-4 deg or 1e-6",
       "frame offset in the recipe's convention, fixed point"),
    _f("offset_real", IR_OFFSET_FLOAT, "REAL", 6, "mm; deg or rad", "the same offset as REAL"),
    _f("sigma_translation", IR_SIGMA_TRANS, "DINT", 1, "µm", "1σ of the offset at the grasp point"),
    _f("sigma_rotation", IR_SIGMA_ROT, "DINT", 1, "1e-4 deg", "1σ of the rotation"),
    _f("convention", IR_CONVENTION, "UINT", 1, "", "robot convention code of the recipe"),
    _f("word_order", IR_WORD_ORDER, "UINT", 1, "", "0 = ABCD, 1 = CDAB"),
    _f("test_real", IR_TEST_FLOAT, "REAL", 1, "", f"always {TEST_FLOAT}: checks REAL decoding"),
    _f("test_dint", IR_TEST_INT, "DINT", 1, "", f"always {TEST_INT}: checks DINT decoding"),
    _f("verify_result_id", IR_VERIFY_RESULT_ID, "UDINT", 1, "", "the last verify's record id"),
    _f("verify_verdict", IR_VERIFY_VERDICT, "UINT", 1, "", "0 none, 1 passed, 2 failed"),
    _f("reserved_53", IR_VERIFY_RESERVED_53, "WORD", 1, "", "0"),
    _f("verify_difference", IR_VERIFY_DIFFERENCE, "REAL", 6, "mm; deg or rad",
       "the verify part's difference to its taught pose"),
    _f("verify_displacement", IR_VERIFY_DISPLACEMENT, "REAL", 1, "mm", "at the grasp point"),
    _f("verify_rotation", IR_VERIFY_ROTATION, "REAL", 1, "deg", "rotation angle"),
    _f("handeye_poses", IR_HANDEYE_POSES, "UINT", 1, "", "poses the hand-eye session holds"),
    _f("handeye_pose", IR_HANDEYE_POSE, "UINT", 1, "", "the pose the last hand-eye step was about"),
    _f("handeye_version", IR_HANDEYE_VERSION, "UDINT", 1, "",
       "the calibration version a calculate stored (waits for activation)"),
    _f("handeye_sigma_translation", IR_HANDEYE_SIGMA_TRANS, "REAL", 1, "mm",
       "1σ of the hand-eye translation"),
    _f("handeye_sigma_rotation", IR_HANDEYE_SIGMA_ROT, "REAL", 1, "deg",
       "1σ of the hand-eye rotation"),
    _f("handeye_holdout_rms", IR_HANDEYE_HOLDOUT_PX, "REAL", 1, "px",
       "reprojection RMS of the held-out poses"),
    _f("handeye_holdout_translation", IR_HANDEYE_HOLDOUT_MM, "REAL", 1, "mm",
       "largest held-out flange pose error"),
    _f("handeye_holdout_rotation", IR_HANDEYE_HOLDOUT_DEG, "REAL", 1, "deg",
       "largest held-out flange rotation error"),
)

#: the PLC's outputs (mvpose reads them)
OUTPUT: Final = Block("output", OUTPUT_SIZE, OUTPUT_FIELDS)
#: the PLC's inputs (mvpose writes them)
INPUT: Final = Block("input", INPUT_SIZE, INPUT_FIELDS)
