"""Codecs of the layout's words: 32-bit integers and floats in ABCD/CDAB word order, ASCII text,
scaled poses."""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence

from mvpose_core.transforms import RobotConvention

from .layout import WordOrder

_INT32_MIN = -(2**31)
_INT32_MAX = 2**31 - 1


def _words(raw: bytes, order: WordOrder) -> list[int]:
    hi, lo = struct.unpack(">HH", raw)
    return [hi, lo] if order is WordOrder.ABCD else [lo, hi]


def _raw(regs: Sequence[int], order: WordOrder) -> bytes:
    if len(regs) != 2:
        raise ValueError(f"a 32-bit value needs 2 registers, got {len(regs)}: {list(regs)}")
    first, second = regs
    hi, lo = (first, second) if order is WordOrder.ABCD else (second, first)
    return struct.pack(">HH", hi, lo)


def encode_int32(value: int, order: WordOrder) -> list[int]:
    """Two registers holding a signed 32-bit integer."""
    if not _INT32_MIN <= value <= _INT32_MAX:
        raise ValueError(f"int32 value {value} out of range")
    return _words(struct.pack(">i", value), order)


def decode_int32(regs: Sequence[int], order: WordOrder) -> int:
    return int(struct.unpack(">i", _raw(regs, order))[0])


def encode_uint32(value: int, order: WordOrder) -> list[int]:
    """Two registers holding an unsigned 32-bit integer."""
    if not 0 <= value <= 2**32 - 1:
        raise ValueError(f"uint32 value {value} out of range")
    return _words(struct.pack(">I", value), order)


def decode_uint32(regs: Sequence[int], order: WordOrder) -> int:
    return int(struct.unpack(">I", _raw(regs, order))[0])


def encode_float32(value: float, order: WordOrder) -> list[int]:
    """Two registers holding an IEEE 754 single."""
    return _words(struct.pack(">f", value), order)


def decode_float32(regs: Sequence[int], order: WordOrder) -> float:
    return float(struct.unpack(">f", _raw(regs, order))[0])


def encode_ascii(text: str, n_regs: int) -> list[int]:
    """Text as registers: two characters each, the first in the high byte, NUL padded."""
    raw = text.encode("ascii")
    if len(raw) > 2 * n_regs:
        raise ValueError(f"text {text!r} has {len(raw)} characters, room for {2 * n_regs}")
    raw = raw.ljust(2 * n_regs, b"\0")
    return list(struct.unpack(f">{n_regs}H", raw))


def decode_ascii(regs: Sequence[int]) -> str:
    """Inverse of encode_ascii; trailing NULs and spaces are dropped, non-ASCII bytes become '?'."""
    raw = struct.pack(f">{len(regs)}H", *regs)
    return raw.split(b"\0", 1)[0].decode("ascii", errors="replace").replace("\ufffd", "?").rstrip()


# --------------------------------------------------------------------------- poses on 6 registers

# Integer scale per value of the 6-value PLC form: counts per unit of the float form.
# Lengths are always µm on the integer block; Euler angles 1e-4 deg; quaternion components and
# rotation-vector radians 1e-6 (1e-4 would be ~0.01 deg, too coarse for a quaternion).
_SCALES: dict[RobotConvention, tuple[float, ...]] = {
    RobotConvention.FANUC: (1e3, 1e3, 1e3, 1e4, 1e4, 1e4),
    RobotConvention.YASKAWA: (1e3, 1e3, 1e3, 1e4, 1e4, 1e4),
    RobotConvention.KUKA: (1e3, 1e3, 1e3, 1e4, 1e4, 1e4),
    RobotConvention.ABB: (1e3, 1e3, 1e3, 1e6, 1e6, 1e6),
    RobotConvention.UR: (1e6, 1e6, 1e6, 1e6, 1e6, 1e6),  # metres → µm, radians → µrad
}


def convention_from_code(code: int) -> RobotConvention:
    """The robot convention behind its PLC code (register 44)."""
    for conv in RobotConvention:
        if conv.code == code:
            return conv
    known = {c.code: c.value for c in RobotConvention}
    raise ValueError(f"robot convention code {code} unknown; known: {known}")


def int_scales(convention: RobotConvention | str) -> tuple[float, ...]:
    """Counts per unit for each of the 6 values on the int32 block."""
    return _SCALES[RobotConvention(convention)]


def pose_to_plc(values: Sequence[float], convention: RobotConvention | str) -> tuple[float, ...]:
    """A robot convention's pose vector as the 6 values of the PLC form.

    Every convention but ABB has 6 values and passes through. ABB's X Y Z q1 q2 q3 q4 becomes
    X Y Z q2 q3 q4 with the sign chosen so that q1 ≥ 0; the PLC recovers
    q1 = sqrt(1 - q2² - q3² - q4²).
    """
    conv = RobotConvention(convention)
    v = [float(x) for x in values]
    if len(v) != conv.size:
        raise ValueError(f"a {conv.value} pose has {conv.size} values {conv.labels}, got {len(v)}")
    if conv is not RobotConvention.ABB:
        return tuple(v)
    q = v[3:]
    n = math.sqrt(sum(c * c for c in q))
    if not n > 0:
        raise ValueError(f"abb quaternion {q} has zero or non-finite norm")
    sign = -1.0 if q[0] < 0 else 1.0
    return (v[0], v[1], v[2], *(sign * c / n for c in q[1:]))


def plc_to_pose(values: Sequence[float], convention: RobotConvention | str) -> tuple[float, ...]:
    """Inverse of pose_to_plc: the convention's full pose vector (7 values for ABB)."""
    conv = RobotConvention(convention)
    v = [float(x) for x in values]
    if len(v) != 6:
        raise ValueError(f"the PLC form of a pose has 6 values, got {len(v)}")
    if conv is not RobotConvention.ABB:
        return tuple(v)
    s = sum(c * c for c in v[3:])
    if s > 1.0 + 1e-6:
        raise ValueError(f"abb quaternion vector part {v[3:]} has norm² {s:.6f} > 1")
    return (v[0], v[1], v[2], math.sqrt(max(0.0, 1.0 - s)), *v[3:])


def encode_pose_int(
    values: Sequence[float], convention: RobotConvention | str, order: WordOrder
) -> list[int]:
    """The 6 PLC-form values as 12 registers of scaled int32."""
    regs: list[int] = []
    for x, scale in zip(values, int_scales(convention), strict=True):
        regs += encode_int32(round(x * scale), order)
    return regs


def decode_pose_int(
    regs: Sequence[int], convention: RobotConvention | str, order: WordOrder
) -> tuple[float, ...]:
    if len(regs) != 12:
        raise ValueError(f"a pose needs 12 registers, got {len(regs)}")
    scales = int_scales(convention)
    return tuple(decode_int32(regs[2 * i : 2 * i + 2], order) / scales[i] for i in range(6))


def encode_pose_float(values: Sequence[float], order: WordOrder) -> list[int]:
    """The 6 PLC-form values as 12 registers of float32."""
    regs: list[int] = []
    for x in values:
        regs += encode_float32(x, order)
    return regs


def decode_pose_float(regs: Sequence[int], order: WordOrder) -> tuple[float, ...]:
    if len(regs) != 12:
        raise ValueError(f"a pose needs 12 registers, got {len(regs)}")
    return tuple(decode_float32(regs[2 * i : 2 * i + 2], order) for i in range(6))


def fits_int32(values: Sequence[float], convention: RobotConvention | str) -> bool:
    """Whether every scaled value is finite and fits an int32 (the check before encoding)."""
    for x, scale in zip(values, int_scales(convention), strict=True):
        if not math.isfinite(x) or not _INT32_MIN <= round(x * scale) <= _INT32_MAX:
            return False
    return True
