"""A stored measurement's body read back: the whole record, its summary, or its residuals.

The body is the canonical JSON envelope the chain hashes (server/store/chain.py). Each reader
builds only what it needs, in one pass by pydantic-core (about 3x faster than json.loads +
validate, which matters: reads share the GIL with the trigger thread): the REST lists a
summary (about 3x cheaper than the whole record), the drift watch only the per-camera
residuals (about a fifth).
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, ConfigDict

from server.store.schemas import (
    CameraResidual,
    MeasurementRecord,
    MeasurementSummary,
    Offset,
    RecordResiduals,
    Residuals,
    StoredMeasurement,
    Uncertainty,
)


class Envelope(BaseModel):
    """The hashed body."""

    station: str
    seq: int
    stored_at: datetime
    record: MeasurementRecord


class _SummaryRecord(BaseModel):
    model_config = ConfigDict(extra="ignore")  # detections and images are skipped, not built

    message: str | None = None
    calibration_id: str | None = None
    calibration_hash: str | None = None
    offset: Offset | None = None
    uncertainty: Uncertainty | None = None
    residuals: Residuals | None = None
    timings_ms: dict[str, float] = {}


class _SummaryEnvelope(BaseModel):
    record: _SummaryRecord


class _ResidualsRecord(BaseModel):
    model_config = ConfigDict(extra="ignore")  # only what the drift watch reads is built

    recipe: str
    triggered_at: datetime
    calibration_id: str | None = None
    calibration_hash: str | None = None
    camera_residuals: list[CameraResidual] | None = None


class _ResidualsEnvelope(BaseModel):
    record: _ResidualsRecord


def summary_of(r: Any) -> MeasurementSummary:
    """A row's summary: its columns and the record's figures, detections and images skipped."""
    rec = _SummaryEnvelope.model_validate_json(r.body).record
    return MeasurementSummary.model_construct(
        id=r.id,
        seq=r.seq,
        stored_at=r.stored_at,
        triggered_at=r.triggered_at,
        trigger_id=r.trigger_id,
        part_id=r.part_id,
        recipe=r.recipe,
        recipe_version=r.recipe_version,
        result=r.result,
        reason_code=r.reason_code,
        reason=r.reason,
        message=rec.message,
        calibration_id=rec.calibration_id,
        calibration_hash=rec.calibration_hash,
        offset=rec.offset,
        uncertainty=rec.uncertainty,
        residuals=rec.residuals,
        timings_ms=rec.timings_ms,
        total_ms=rec.timings_ms.get("total"),
        hash=r.hash,
    )


def stored_of(r: Any) -> StoredMeasurement:
    """A row's whole stored record."""
    env = envelope(r.body)
    return StoredMeasurement.model_construct(
        id=r.id,
        seq=r.seq,
        stored_at=r.stored_at,
        prev_hash=r.prev_hash,
        hash=r.hash,
        record=env.record,
    )


def envelope(body: str) -> Envelope:
    """The whole body, its record validated."""
    return Envelope.model_validate_json(body)


def residuals_of(r: Any) -> RecordResiduals:
    """What the drift watch reads of a row (its ``id`` and ``body``)."""
    rec = _ResidualsEnvelope.model_validate_json(r.body).record
    return RecordResiduals(r.id, rec.recipe, rec.triggered_at, rec.calibration_id,
                           rec.calibration_hash, rec.camera_residuals or [])
