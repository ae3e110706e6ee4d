"""The result event: one recorded answer, typed and frozen, as every outlet shows it.

The station builds it once from the stored record (``server.store.events``: drivers may not read
the store's types) and every outlet derives from it: the link's outcome
(:meth:`drivers.links.base.LinkOutcome.from_event`), the OPC UA event, LastResult and result
methods, the MQTT payload, the control channel's trigger answer (so the REST trigger answer) and
the CSV export. Where it crosses a process (the control channel, the OPC UA link's child, the MQTT
payload) it is :meth:`ResultEvent.to_json`'s shape and nothing else.

A field whose metadata is :data:`SHOWN` is also shown by the outlets that have a fixed list of
columns or nodes (a CSV column named after the field, an OPC UA LastResult variable and event
property named after it in CamelCase); the outlets that carry the whole event (MQTT, REST) show
every field anyway. A new field is therefore added here and in the builder, nowhere else.
"""

from __future__ import annotations

import json
import types
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from datetime import datetime
from functools import cache
from typing import Any, Union, get_args, get_origin, get_type_hints

SHOWN: Mapping[str, Any] = {"shown": True}  # field metadata: a column / node of its own


@dataclass(frozen=True)
class ResultEvent:
    """One recorded answer of the station (its record's seq is ``result_id``)."""

    result_id: int  # the record's seq in the station's chain: never reused
    trigger_id: int  # the controller's trigger id, as recorded
    part_id: str | None  # VIN or data-matrix code; None when the trigger named none
    result: str  # "OK" or "NOK"
    reason_code: int  # mvpose_core.reasons.Reason (0 = OK)
    reason: str  # the code's name
    message: str  # the gate's one-line why ("" when it said nothing)
    triggered_at: datetime  # aware, UTC
    recipe: str
    recipe_version: int
    # the offset as the robot program reads it: the recipe's convention, full precision, in
    # length_unit and angle_unit; a NOK result keeps its offset for diagnosis only (robot_offset)
    convention: str | None
    offset: tuple[float, ...] | None
    sigma_mm: float | None  # 1σ at the grasp point, total (None: the record has no 1σ)
    sigma_deg: float | None
    sigma_detector_mm: float | None = None  # its two parts (docs/engine.md), when recorded
    sigma_detector_deg: float | None = None
    sigma_calibration_mm: float | None = None
    sigma_calibration_deg: float | None = None
    processing_ms: float | None = None  # the record's total time (timings_ms["total"])
    timings_ms: Mapping[str, float] = field(default_factory=dict)  # stage -> ms, as recorded
    calibration_id: str | None = None
    calibration_sha256: str | None = None
    stored_at: datetime | None = None  # when the record was sealed (None: not known here)
    hash: str | None = None  # the record's chain hash (None: not known here)
    views: int | None = None  # views with detections (None: not known from a summary)
    final: bool = True  # every recorded answer ends its trigger's sequence
    length_unit: str = "mm"
    angle_unit: str = "deg"
    # the pose fit's RMS reprojection residual over every used observation, px (None: no fit)
    residual_rms_px: float | None = field(default=None, metadata=SHOWN)

    @property
    def ok(self) -> bool:
        return self.reason_code == 0 and self.result == "OK"

    @property
    def robot_offset(self) -> tuple[float, ...] | None:
        """The offset a robot may use: None unless OK."""
        return self.offset if self.ok else None

    # ------------------------------------------------------------------ the one shape
    def to_dict(self) -> dict[str, Any]:
        """JSON-able: datetimes as ISO 8601, tuples as lists."""
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), separators=(",", ":"), allow_nan=False)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ResultEvent:
        """The event :meth:`to_dict` gave; raises ValueError naming what does not fit."""
        hints = _hints()
        unknown = sorted(set(data) - set(hints))
        if unknown:
            raise ValueError(f"result event: unknown field(s) {', '.join(unknown)}")
        values = {}
        for name, value in data.items():
            try:
                values[name] = _typed(hints[name], value)
            except (TypeError, ValueError) as err:
                raise ValueError(f"result event: field {name!r} = {value!r}: {err}") from None
        try:
            return cls(**values)
        except TypeError as err:
            raise ValueError(f"result event: {err}") from None

    @classmethod
    def from_json(cls, text: str | bytes) -> ResultEvent:
        data = json.loads(text)
        if not isinstance(data, dict):
            raise ValueError(f"result event: expected a JSON object, got {type(data).__name__}")
        return cls.from_dict(data)

    @staticmethod
    def shown() -> list[tuple[str, type]]:
        """The SHOWN fields and their value types (None removed from an optional one), in
        order: what outlets with a fixed list of columns or nodes append."""
        return [(f.name, _base(_hints()[f.name])) for f in fields(ResultEvent)
                if f.metadata.get("shown")]


@cache
def _hints() -> dict[str, Any]:
    return get_type_hints(ResultEvent)


def _base(tp: Any) -> Any:
    """``X`` of ``X | None``; other types as they are."""
    if get_origin(tp) in (Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return tp


def _plain(value: Any) -> Any:
    if isinstance(value, datetime):
        return value.isoformat()
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


def _typed(tp: Any, value: Any) -> Any:
    if value is None:
        if _base(tp) is tp:
            raise ValueError("must not be null")
        return None
    base = _base(tp)
    origin = get_origin(base)
    if base is datetime:
        if isinstance(value, datetime):
            return value
        when = datetime.fromisoformat(str(value))
        if when.tzinfo is None:
            raise ValueError("a time without its zone")
        return when
    if origin is tuple:
        return tuple(float(v) for v in value)
    if origin is Mapping or base is Mapping:
        return {str(k): float(v) for k, v in dict(value).items()}
    if base is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise TypeError("expected a number")
        return float(value)
    if base in (int, bool, str) and type(value) is not base:
        raise TypeError(f"expected {base.__name__}")
    return value
