"""The result event: built once from a stored record (or its summary), one JSON shape, and the
outcome a link gives derived from it."""

from __future__ import annotations

import dataclasses
import json
from datetime import UTC, datetime

import numpy as np
import pytest
from records import make_record

from drivers.links.base import LinkOutcome
from drivers.links.result import ResultEvent
from mvpose_core.reasons import Reason
from server.store.events import record_event, summary_event
from server.store.schemas import MeasurementRecord, MeasurementSummary

STORED_AT = datetime(2026, 11, 2, 7, 0, tzinfo=UTC)


def _summary(seq: int, rec_json: dict[str, object]) -> MeasurementSummary:
    rec = rec_json
    return MeasurementSummary.model_validate({
        "id": 9, "seq": seq, "stored_at": STORED_AT, "hash": "ab" * 32,
        **{k: rec[k] for k in ("triggered_at", "trigger_id", "part_id", "recipe",
                               "recipe_version", "result", "reason_code", "reason", "message",
                               "calibration_id", "calibration_hash", "offset", "uncertainty",
                               "residuals", "timings_ms")}})


def test_an_ok_records_event_and_its_summarys_are_the_same_but_for_views() -> None:
    rec = make_record(np.random.default_rng(1), trigger_id=7)
    event = record_event(rec, 41, stored_at=STORED_AT, hash="ab" * 32)
    assert (event.result_id, event.trigger_id, event.part_id) == (41, 7, "VIN000007")
    assert event.residual_rms_px == (rec.residuals.rms_px if rec.residuals else None)
    assert event.ok and event.robot_offset == tuple(rec.offset.values)
    assert (event.convention, event.length_unit, event.angle_unit) == ("fanuc", "mm", "deg")
    assert event.sigma_mm == rec.uncertainty.sigma_mm
    assert event.processing_ms == rec.timings_ms["total"] and event.views == 1
    from_summary = summary_event(_summary(41, rec.model_dump(mode="json")))
    assert from_summary == dataclasses.replace(event, views=None)


def test_a_nok_event_keeps_its_offset_for_diagnosis_but_gives_the_robot_none() -> None:
    ok_rec = make_record(np.random.default_rng(2))
    rec = ok_rec.model_copy(update={  # a NOK record that kept its pose (the quality gate's)
        **MeasurementRecord.reason_fields(Reason.TOO_FEW_MARKS), "message": "2 of 3 marks"})
    event = record_event(rec, 3)
    assert not event.ok and event.reason == "TOO_FEW_MARKS" and event.message == "2 of 3 marks"
    assert event.offset == tuple(ok_rec.offset.values) and event.robot_offset is None
    out = LinkOutcome.from_event(event, processing_ms=4.5)
    assert (out.result_code, out.result_id, out.offset, out.processing_ms) == (
        int(Reason.TOO_FEW_MARKS), 3, None, 4.5)
    ok = record_event(make_record(np.random.default_rng(3)), 4)
    out = LinkOutcome.from_event(ok, processing_ms=9.0)
    assert out.offset == ok.offset and out.sigma_trans_mm == ok.sigma_mm and out.final


def test_the_json_shape_round_trips_and_names_what_does_not_fit() -> None:
    event = record_event(make_record(np.random.default_rng(4)), 12, stored_at=STORED_AT)
    text = event.to_json()
    assert ResultEvent.from_json(text) == event
    data = json.loads(text)
    assert data["triggered_at"].endswith("+00:00") and isinstance(data["offset"], list)
    with pytest.raises(ValueError, match="unknown field.*colour"):
        ResultEvent.from_dict({**data, "colour": "red"})
    with pytest.raises(ValueError, match="'residual_rms_px'"):
        ResultEvent.from_dict({**data, "residual_rms_px": "twelve"})
    with pytest.raises(ValueError, match="'result_id'.*must not be null"):
        ResultEvent.from_dict({**data, "result_id": None})
    with pytest.raises(ValueError, match="'triggered_at'.*zone"):
        ResultEvent.from_dict({**data, "triggered_at": "2026-11-02T06:00:00"})
    missing = {k: v for k, v in data.items() if k != "recipe"}
    with pytest.raises(ValueError, match="recipe"):
        ResultEvent.from_dict(missing)
    with pytest.raises(ValueError, match="JSON object"):
        ResultEvent.from_json("[1]")


def test_the_shown_fields_are_the_fits_residual() -> None:
    assert ResultEvent.shown() == [("residual_rms_px", float)]
