"""The result event of a stored record: the one place a :class:`ResultEvent` is built.

The station builds it when it has appended a record (the listeners, the link's outcome, the
control channel's answer), the MQTT outbox when the record goes into the database, the station's
result queries (OPC UA GetResultById ...) and the CSV export from a record's summary. All of them
go through :func:`result_event`, so a field added to the event is filled here once.
"""

from __future__ import annotations

from collections.abc import Mapping
from datetime import datetime
from typing import Protocol

from drivers.links.result import ResultEvent
from server.store.schemas import (
    MeasurementRecord,
    MeasurementSummary,
    Offset,
    Residuals,
    Uncertainty,
)


class RecordFields(Protocol):
    """What a stored record and its summary both hold."""

    @property
    def trigger_id(self) -> int: ...
    @property
    def part_id(self) -> str | None: ...
    @property
    def triggered_at(self) -> datetime: ...
    @property
    def recipe(self) -> str: ...
    @property
    def recipe_version(self) -> int: ...
    @property
    def calibration_id(self) -> str | None: ...
    @property
    def calibration_hash(self) -> str | None: ...
    @property
    def result(self) -> str: ...
    @property
    def reason_code(self) -> int: ...
    @property
    def reason(self) -> str: ...
    @property
    def message(self) -> str | None: ...
    @property
    def offset(self) -> Offset | None: ...
    @property
    def uncertainty(self) -> Uncertainty | None: ...
    @property
    def timings_ms(self) -> Mapping[str, float]: ...
    @property
    def residuals(self) -> Residuals | None: ...


def result_event(rec: RecordFields, *, seq: int, stored_at: datetime | None = None,
                 hash: str | None = None, views: int | None = None) -> ResultEvent:  # noqa: A002
    """The event of the record ``rec`` sealed as ``seq`` of its station's chain."""
    unc = rec.uncertainty
    return ResultEvent(
        result_id=seq, trigger_id=rec.trigger_id, part_id=rec.part_id, result=rec.result,
        reason_code=rec.reason_code, reason=rec.reason, message=rec.message or "",
        triggered_at=rec.triggered_at, recipe=rec.recipe, recipe_version=rec.recipe_version,
        convention=rec.offset.convention.value if rec.offset is not None else None,
        offset=tuple(rec.offset.values) if rec.offset is not None else None,
        sigma_mm=unc.sigma_mm if unc else None, sigma_deg=unc.sigma_deg if unc else None,
        sigma_detector_mm=unc.detector_mm if unc else None,
        sigma_detector_deg=unc.detector_deg if unc else None,
        sigma_calibration_mm=unc.calibration_mm if unc else None,
        sigma_calibration_deg=unc.calibration_deg if unc else None,
        processing_ms=rec.timings_ms.get("total"), timings_ms=dict(rec.timings_ms),
        calibration_id=rec.calibration_id, calibration_sha256=rec.calibration_hash,
        stored_at=stored_at, hash=hash, views=views,
        residual_rms_px=rec.residuals.rms_px if rec.residuals is not None else None,
    )


def record_event(record: MeasurementRecord, seq: int, stored_at: datetime | None = None,
                 hash: str | None = None) -> ResultEvent:  # noqa: A002
    """The event of a whole record (the station, the outbox): with its views."""
    return result_event(record, seq=seq, stored_at=stored_at, hash=hash,
                        views=len({d.view for d in record.detections}) or None)


def summary_event(summary: MeasurementSummary) -> ResultEvent:
    """The event of a record's summary (queries, the CSV export): views unknown."""
    return result_event(summary, seq=summary.seq, stored_at=summary.stored_at,
                        hash=summary.hash)
