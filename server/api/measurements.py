"""Measurements endpoints: filtered cursor paging, CSV/JSON export, one record, images, chain."""

from __future__ import annotations

import csv
import io
from collections.abc import Iterator
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Path, Query
from fastapi.responses import FileResponse, Response, StreamingResponse
from pydantic import BaseModel

from drivers.links.result import ResultEvent
from server.api.deps import IsoDateTime, ReadUser, ServicesDep, StoreDep, json_response
from server.errors import NotFoundError
from server.store.chain import canonical_json
from server.store.events import summary_event
from server.store.schemas import (
    MAX_ID,
    ChainReport,
    ImageStatus,
    MeasurementDetail,
    MeasurementFilter,
    MeasurementSummary,
    StoredMeasurement,
)

router = APIRouter(prefix="/measurements", tags=["measurements"])

# Bounded so an absurd number is the client's 422, not an overflow inside the database driver.
IdPath = Annotated[int, Path(ge=1, le=MAX_ID)]
ViewPath = Annotated[int, Path(ge=1, le=255)]


class MeasurementPage(BaseModel):
    items: list[MeasurementSummary]
    next_cursor: str | None


async def measurement_filter(
    since: Annotated[
        IsoDateTime | None, Query(description="triggered at or after (ISO 8601, with zone)")
    ] = None,
    until: Annotated[
        IsoDateTime | None, Query(description="triggered before (ISO 8601, with zone)")
    ] = None,
    result: Literal["OK", "NOK"] | None = None,
    reason_code: Annotated[int | None, Query(ge=0, le=65535)] = None,
    recipe: Annotated[str | None, Query(max_length=64)] = None,
    part_id: Annotated[str | None, Query(max_length=64)] = None,
    result_id: Annotated[
        int | None, Query(ge=1, le=MAX_ID, description="the result id the PLC read (= seq)")
    ] = None,
) -> MeasurementFilter:
    return MeasurementFilter(
        since=since,
        until=until,
        result=result,
        reason_code=reason_code,
        recipe=recipe,
        part_id=part_id,
        result_id=result_id,
    )


FilterDep = Annotated[MeasurementFilter, Depends(measurement_filter)]


@router.get("", response_model=MeasurementPage)
def list_measurements(
    _: ReadUser,
    store: StoreDep,
    filters: FilterDep,
    cursor: Annotated[str | None, Query(max_length=200)] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> Response:
    """Measurements, newest first; pass next_cursor back as cursor for the next page."""
    items, next_cursor = store.measurements.summary_page(filters, cursor, limit)
    return json_response(MeasurementPage(items=items, next_cursor=next_cursor))


CSV_COLUMNS = [
    "id",
    "seq",
    "triggered_at",
    "stored_at",
    "trigger_id",
    "part_id",
    "recipe",
    "recipe_version",
    "result",
    "reason_code",
    "reason",
    "convention",
    "o1",
    "o2",
    "o3",
    "o4",
    "o5",
    "o6",
    "o7",
    "sigma_mm",
    "sigma_deg",
    "rms_px",
    "max_px",
    "total_ms",
    "calibration_id",
    "calibration_hash",
    "timings_ms",
    "hash",
    "result_id",  # = seq; after the older columns, so that they keep their positions
    # then the result event's SHOWN fields, in the event's order (drivers/links/result.py)
    *(name for name, _ in ResultEvent.shown()),
]


def _csv_row(m: MeasurementSummary) -> list[object]:
    event = summary_event(m)
    values: list[object] = list(m.offset.values) if m.offset else []
    values += [""] * (7 - len(values))
    return [
        m.id,
        m.seq,
        m.triggered_at.isoformat(),
        m.stored_at.isoformat(),
        m.trigger_id,
        m.part_id or "",
        m.recipe,
        m.recipe_version,
        m.result,
        m.reason_code,
        m.reason,
        m.offset.convention.value if m.offset else "",
        *values,
        m.uncertainty.sigma_mm if m.uncertainty else "",
        m.uncertainty.sigma_deg if m.uncertainty else "",
        m.residuals.rms_px if m.residuals else "",
        m.residuals.max_px if m.residuals else "",
        "" if m.total_ms is None else m.total_ms,
        m.calibration_id or "",
        m.calibration_hash or "",
        canonical_json(m.timings_ms),
        m.hash,
        m.seq,
        *("" if (x := getattr(event, name)) is None else x for name, _ in ResultEvent.shown()),
    ]


def _csv_stream(rows: Iterator[MeasurementSummary]) -> Iterator[str]:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for m in rows:
        writer.writerow(_csv_row(m))
        if buf.tell() > 65536:
            yield buf.getvalue()
            buf.seek(0)
            buf.truncate()
    yield buf.getvalue()


def _json_stream(rows: Iterator[StoredMeasurement]) -> Iterator[str]:
    yield "["
    for i, m in enumerate(rows):
        yield ("," if i else "") + "\n" + m.model_dump_json()
    yield "\n]\n"


@router.get(
    "/export",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/csv": {}, "application/json": {}}}},
)
def export_measurements(
    _: ReadUser,
    store: StoreDep,
    filters: FilterDep,
    format: Literal["csv", "json"] = "csv",  # noqa: A002
) -> StreamingResponse:
    """Every matching measurement, oldest first, as CSV (one row each) or a JSON array."""
    # Sync generators: Starlette pulls them in the threadpool, so export never blocks the loop.
    body: Iterator[str]
    if format == "csv":
        body = _csv_stream(store.measurements.iterate_summaries(filters))
        media = "text/csv; charset=utf-8"
    else:
        body, media = _json_stream(store.measurements.iterate(filters)), "application/json"
    name = f"measurements-{store.station}.{format}"
    return StreamingResponse(
        body, media_type=media, headers={"Content-Disposition": f'attachment; filename="{name}"'}
    )


@router.get("/chain", response_model=ChainReport)
def verify_chain(_: ReadUser, store: StoreDep) -> ChainReport:
    """Recompute the hash chain of this station's measurements and report the first bad link."""
    return store.measurements.verify_chain()


@router.get("/{measurement_id}", response_model=MeasurementDetail)
def get_measurement(
    measurement_id: IdPath, _: ReadUser, services: ServicesDep
) -> Response:
    """One measurement with its detections per camera and the state of its images."""
    m = services.store.measurements.get(measurement_id)
    rows = {(i.view, i.camera_id): i for i in services.store.images.for_measurement(m.id)}
    status = []
    for ref in m.record.images:
        row = rows.get((ref.view, ref.camera_id))
        state: Literal["stored", "evicted", "pending"] = (
            "pending" if row is None else ("evicted" if row.evicted_at else "stored")
        )
        status.append(
            ImageStatus(
                view=ref.view,
                camera_id=ref.camera_id,
                path=ref.path,
                state=state,
                bytes=row.bytes if row else None,
            )
        )
    return json_response(MeasurementDetail.model_construct(
        id=m.id, seq=m.seq, stored_at=m.stored_at, prev_hash=m.prev_hash, hash=m.hash,
        record=m.record, image_status=status))


@router.get(
    "/{measurement_id}/images/{view}/{camera_id}",
    response_class=FileResponse,
    responses={200: {"content": {"image/png": {}}}},
)
def get_image(
    measurement_id: IdPath,
    view: ViewPath,
    camera_id: Annotated[str, Path(max_length=64)],
    _: ReadUser,
    services: ServicesDep,
) -> FileResponse:
    """An archived frame as PNG (404 once it has been evicted; the record stays)."""
    m = services.store.measurements.get(measurement_id)
    for i in services.store.images.for_measurement(m.id):
        if i.view == view and i.camera_id == camera_id:
            if i.evicted_at is not None:
                raise NotFoundError(
                    f"image of measurement {m.id} view {view} camera {camera_id!r} "
                    f"was evicted at {i.evicted_at.isoformat()}"
                )
            return FileResponse(services.images.resolve(i.path), media_type="image/png")
    raise NotFoundError(
        f"measurement {m.id} has no archived image for view {view} camera {camera_id!r}"
    )
