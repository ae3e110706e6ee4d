"""What the operator page reads from the store, through the store's repositories (no SQL here):
records with their overlays, the newest record that kept frames, trend columns, recipes."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np

from mvpose_core.shifts import DEFAULT_SHIFTS, ShiftWindow, shift_at, time_zone
from mvpose_core.station import RecipeConfig
from server.errors import DomainError
from server.state import Services
from server.store.archive import ImageInfo
from server.store.schemas import MeasurementFilter, MeasurementSummary, StoredMeasurement
from server.store.shifts import ShiftCounts
from server.web.geometry import CameraOverlay, Geometry, recipe_from_content
from server.web.i18n import _

#: how far back the Live page looks for a record with archived frames (OK frames are kept 1 in N)
FRAMES_LOOKBACK = 400


@dataclass(frozen=True)
class RecordView:
    """One record as the page shows it: the record, its overlays, which frames are on disk."""

    stored: StoredMeasurement
    recipe: RecipeConfig | None
    overlays: list[CameraOverlay]
    frames: dict[tuple[int, str], ImageInfo]  # archived and not evicted

    @property
    def has_frames(self) -> bool:
        return bool(self.frames)


class Reader:
    """Read side of the page over one process's :class:`Services`. Blocking: call in a thread."""

    def __init__(self, services: Services) -> None:
        self.services = services
        self.geometry = Geometry(services.station)
        self._recipes: dict[tuple[str, int], RecipeConfig | None] = {}
        self._camera_rows: dict[int, dict[str, tuple[float | None, ...]]] = {}
        self._lock = threading.Lock()

    @property
    def store(self) -> Any:
        return self.services.store

    # ------------------------------------------------------------------ records
    def recipe(self, name: str, version: int) -> RecipeConfig | None:
        """A stored recipe version (None if the store has no such version)."""
        key = (name, version)
        if key not in self._recipes:
            try:
                _info, content = self.store.versions.content("recipe", name, version)
                self._recipes[key] = recipe_from_content(name, version, content)
            except (DomainError, ValueError):
                self._recipes[key] = None
        return self._recipes[key]

    def view(self, stored: StoredMeasurement) -> RecordView:
        rec = stored.record
        recipe = self.recipe(rec.recipe, rec.recipe_version)
        frames = {}
        if rec.images:
            frames = {(i.view, i.camera_id): i
                      for i in self.store.images.for_measurement(stored.id)
                      if i.evicted_at is None}
        return RecordView(stored, recipe, self.geometry.overlays(rec, recipe), frames)

    def get(self, measurement_id: int) -> RecordView:
        return self.view(self.store.measurements.get(measurement_id))

    def newest_id(self) -> int | None:
        items, _next = self.store.measurements.summary_page(MeasurementFilter(), None, 1)
        return items[0].id if items else None

    def shift(self, now: datetime | None = None) -> tuple[ShiftWindow, ShiftCounts]:
        """The shift ``now`` is in (the station file's shifts; three from 06:00 UTC without a
        station file) and its counts from the store."""
        station = self.services.station
        shifts = station.shifts if station is not None else DEFAULT_SHIFTS
        zone = time_zone(station.time_zone if station is not None else "UTC")
        window = shift_at(shifts, zone, now or datetime.now(UTC))
        return window, self.store.shifts.counts(window.start, window.end)

    def latest_with_frames(self, lookback: int = FRAMES_LOOKBACK) -> RecordView | None:
        """The newest record whose frames are still in the archive, within ``lookback``."""
        cursor, seen = None, 0
        while seen < lookback:
            page, cursor = self.store.measurements.page(MeasurementFilter(), cursor, 50)
            for stored in page:
                if stored.record.images:
                    view = self.view(stored)
                    if view.has_frames:
                        return view
            seen += len(page)
            if cursor is None:
                break
        return None

    # ------------------------------------------------------------------ trends
    def trends(self, filters: MeasurementFilter, limit: int) -> dict[str, Any]:
        """Columns of the newest ``limit`` matching records, oldest first (uPlot's layout).

        The list comes from the store's summaries (no detections: cheap); each record's
        per-camera residuals need its detections and are computed once per process (records
        never change), from full records read only for the ones not seen before."""
        items: list[MeasurementSummary] = []
        cursor = None
        while len(items) < limit:
            page, cursor = self.store.measurements.summary_page(filters, cursor,
                                                                min(1000, limit - len(items)))
            items += page
            if cursor is None:
                break
        items.reverse()
        self._learn_cameras(filters, [m.id for m in items if m.id not in self._camera_rows])
        cams = [self._camera_rows.get(m.id, {}) for m in items]
        cameras = sorted({c for row in cams for c in row})
        axes = max((len(m.offset.values) for m in items if m.offset), default=6)

        def camera(k: int) -> dict[str, list[float | None]]:
            return {c: [row.get(c, (None, None, None))[k] for row in cams] for c in cameras}

        return {
            "id": [m.id for m in items],
            "t": [m.triggered_at.timestamp() for m in items],
            "result": [m.result for m in items],
            "reason": [m.reason for m in items],
            "offset": [[_r(m.offset.values[k]) if m.offset and k < len(m.offset.values)
                        else None for m in items] for k in range(axes)],
            "sigma_mm": [_r(m.uncertainty.sigma_mm) if m.uncertainty else None for m in items],
            "sigma_deg": [_r(m.uncertainty.sigma_deg) if m.uncertainty else None
                          for m in items],
            "rms_px": [_r(m.residuals.rms_px) if m.residuals else None for m in items],
            "total_ms": [_r(m.total_ms) for m in items],
            "cameras": cameras,
            "camera_rms": camera(0),
            "camera_du": camera(1),
            "camera_dv": camera(2),
        }

    def _learn_cameras(self, filters: MeasurementFilter, ids: list[int]) -> None:
        if not ids:
            return
        todo, lowest, cursor = set(ids), min(ids), None
        while todo:
            page, cursor = self.store.measurements.page(filters, cursor, 500)
            for s in page:
                if s.id in todo:
                    self._camera_rows[s.id] = self._camera_row(s)
                    todo.discard(s.id)
            if cursor is None or (page and page[-1].id <= lowest):
                break
        with self._lock:
            if len(self._camera_rows) > 200_000:
                self._camera_rows.clear()

    def _camera_row(self, s: StoredMeasurement) -> dict[str, tuple[float | None, ...]]:
        """Per camera: (RMS, mean du, mean dv) of the record's reprojection residuals, px: as
        the pipeline recorded them for the drift watch, else recomputed from the detections."""
        rec = s.record
        out: dict[str, tuple[float | None, ...]] = {}
        if rec.camera_residuals:
            for c in rec.camera_residuals:
                key = c.camera_id if c.view == 1 else f"v{c.view}/{c.camera_id}"
                out[key] = (_r(c.rms_px), _r(c.mean_px[0]), _r(c.mean_px[1]))
            return out
        recipe = self.recipe(rec.recipe, rec.recipe_version)
        for ov in self.geometry.overlays(rec, recipe):
            mean = ov.mean_residual
            key = ov.camera_id if ov.view == 1 else f"v{ov.view}/{ov.camera_id}"
            out[key] = (_r(ov.rms_px), _r(mean[0]) if mean else None,
                        _r(mean[1]) if mean else None)
        return out

    # ------------------------------------------------------------------ recipes
    def active_recipe_of(self, name: str) -> RecipeConfig | None:
        for n in self.store.versions.names("recipe"):
            if n.name == name and n.active_version is not None:
                return self.recipe(n.name, n.active_version)
        return None

    def active_recipe(self) -> tuple[str, int, RecipeConfig | None] | None:
        names = self.store.versions.names("recipe")
        station = self.services.station
        preferred = station.default_recipe if station is not None else None
        names.sort(key=lambda n: (n.name != preferred, n.name))
        for n in names:
            if n.active_version is not None:
                return n.name, n.active_version, self.recipe(n.name, n.active_version)
        return None


def _r(x: float | None, digits: int = 5) -> float | None:
    if x is None or not np.isfinite(x):
        return None
    return round(float(x), digits)


def age_words(then: datetime, now: datetime) -> str:
    """``3 d 4 h`` / ``5 h 12 min`` / ``40 min``: how long ago, in words an operator reads."""
    s = max((now - then).total_seconds(), 0.0)
    d, rem = divmod(int(s), 86400)
    h, rem = divmod(rem, 3600)
    m = rem // 60
    if d:
        return _("{d} d {h} h").format(d=d, h=h)
    if h:
        return _("{h} h {m} min").format(h=h, m=m)
    return _("{m} min").format(m=m)
