"""Calibration health: the drift watch over the station's records, and the reference-part check.

:class:`DriftService` reads the residuals of the records stored since the last id it has seen
(one query; only ``MeasurementRecord.camera_residuals`` and what names the watch are parsed),
feeds each record's per-camera residual means to a :class:`mvpose_core.drift.DriftWatch` oldest
first, and keeps the watch between calls: a report costs one small query when nothing is new.
One watch runs per (recipe, calibration): a new calibration starts a new learning window. The
station's alarm watch asks for the cameras' states only (:meth:`DriftService.cameras`): its
rounds run in the station process, where any Python holds the GIL the trigger thread needs.

:func:`verify_reference` judges a measurement of the taught reference part: the offset it
implies against the active recipe's taught pose should be ~zero, within the recipe's grasp
tolerances (``tolerances.translation_mm`` and ``tolerances.rotation_deg``).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from typing import Literal

import numpy as np
from pydantic import BaseModel, Field

from mvpose_core.drift import (
    CameraDrift,
    DriftOptions,
    DriftWatch,
    drift_message,
    siegmund_arl,
)
from mvpose_core.drift_history import history_bytes
from mvpose_core.estimate import Observation
from mvpose_core.measure import Measurement
from mvpose_core.offset import frame_offsets
from mvpose_core.residuals import camera_residuals, shift_response
from mvpose_core.station import RecipeConfig, StationConfig
from server.errors import ConflictError, NotFoundError
from server.store import Store
from server.store.schemas import (
    CameraResidual,
    MeasurementFilter,
    MeasurementRecord,
    Offset,
    RecordResiduals,
)

Status = Literal["learning", "ok", "warning", "alarm"]
Response = dict[tuple[int, str], dict[tuple[int, str], np.ndarray]]
_RANK = {"learning": 0, "ok": 1, "warning": 2, "alarm": 3}


def record_camera_residuals(
    observations: Sequence[Observation], measurement: Measurement
) -> list[CameraResidual]:
    """The record's ``camera_residuals`` from a trigger's observations and its measurement.

    ``observations`` are the ones given to :func:`mvpose_core.measure.measure` (the last call,
    when the pipeline measures twice).
    """
    return [
        CameraResidual(
            view=c.view,
            camera_id=c.camera_id,
            mean_px=(round(c.mean_px[0], 6), round(c.mean_px[1], 6)),
            rms_px=round(c.rms_px, 6),
            count=c.count,
            used=c.used,
        )
        for c in camera_residuals(observations, measurement.pose)
    ]


# ----------------------------------------------------------------------------- response models


class DriftRule(BaseModel):
    """The rule's constants and what they mean (docs/calibration.md, "Drift watch")."""

    k: float = Field(description="CUSUM reference value, σ")
    h_warn: float = Field(description="warning threshold, σ")
    h_alarm: float = Field(description="alarm threshold, σ")
    warmup: int = Field(description="triggers per camera that learn its noise level")
    arl0_warn: float = Field(description="in-control run length of one one-sided statistic to "
                             "a warning, triggers (known noise level; a camera has 4)")
    arl0_alarm: float = Field(description="the same to an alarm, triggers")


class DriftPoint(BaseModel):
    """One trigger of one camera in the trend."""

    id: int
    triggered_at: datetime
    du_px: float = Field(description="mean residual along u, px")
    dv_px: float = Field(description="mean residual along v, px")
    statistic: float = Field(description="largest CUSUM statistic after it, σ")


class CameraDriftReport(BaseModel):
    """One camera's drift state and its recent trend."""

    view: int
    camera_id: str
    status: Status
    message: str = Field(description='e.g. "camera cam2 moved ~0.4 px since 08:12"')
    statistic: float = Field(description="largest one-sided CUSUM statistic, σ")
    moved_camera: str | None = Field(None, description="the camera whose move explains it best")
    moved_view: int | None = None
    shift_px: float | None = Field(None, description="estimated image move of moved_camera, px")
    shift_uv_px: tuple[float, float] | None = Field(None, description="the move as (du, dv), px")
    residual_shift_px: tuple[float, float] | None = Field(
        None, description="this camera's mean residual change since the start, px"
    )
    since: datetime | None = Field(None, description="when the drift started (change point)")
    since_id: int | None = Field(None, description="the measurement it started at")
    triggers: int = Field(description="triggers watched since the noise level was learned")
    learning_left: int = Field(description="triggers still needed to learn the noise level")
    baseline_mean_px: tuple[float, float] | None = None
    baseline_sigma_px: tuple[float, float] | None = None
    trend: list[DriftPoint] = Field(description="the last triggers, oldest first")


class LastVerify(BaseModel):
    """The newest calibration verify (its record has part id ``VERIFY``), judged now."""

    measurement_id: int
    result_id: int
    triggered_at: datetime
    passed: bool | None = Field(description="against the active taught pose and tolerances; "
                                "null: the verify measured no pose")
    message: str


class DriftReport(BaseModel):
    """Calibration health of the station: the drift watch per camera."""

    station: str
    status: Status = Field(description="the worst camera's status (learning without records)")
    recipe: str | None = Field(None, description="recipe of the newest record with residuals")
    calibration_id: str | None = None
    calibration_hash: str | None = None
    calibration_since: datetime | None = Field(
        None, description="first record of this recipe and calibration the watch has seen"
    )
    last_id: int | None = Field(None, description="newest record read")
    records: int = Field(description="records with residuals watched for this recipe and "
                         "calibration")
    messages: list[str] = Field(description="one line per camera in warning or alarm")
    rule: DriftRule
    cameras: list[CameraDriftReport]
    last_verify: LastVerify | None = Field(
        None, description="the newest calibration verify (POST /calibration/verify, Modbus "
        "VERIFY, OPC UA Verify): a watch in alarm is confirmed or cleared by one")


class VerifyReport(BaseModel):
    """A measurement of the reference part against its taught pose."""

    measurement_id: int | None = Field(description="the measurement's database id (null: not "
                                       "committed yet; the result id is the key)")
    result_id: int | None = Field(None, description="the measurement's result id (seq)")
    recipe: str
    recipe_version: int = Field(description="the active version, whose taught pose is checked")
    measured_with_version: int = Field(description="the recipe version of the measurement")
    measurement_result: Literal["OK", "NOK"]
    measurement_reason: str
    passed: bool
    offset: Offset = Field(description="implied offset in the recipe's robot convention")
    grasp_displacement_mm: float
    rotation_deg: float
    limit_mm: float = Field(description="tolerances.translation_mm of the recipe")
    limit_deg: float = Field(description="tolerances.rotation_deg of the recipe")
    margin_mm: float = Field(description="limit − displacement (negative: by how much it fails)")
    margin_deg: float
    message: str


# ----------------------------------------------------------------------------- the service

#: bytes a trigger adds to a segment besides its watch's history: the record id
RECORD_ID_BYTES = 8


def service_history_bytes(cameras: int, history: int) -> int:
    """A segment's history at its cap: the watch's (:func:`mvpose_core.drift.history_bytes`)
    and the record ids of its ``history`` triggers."""
    return history_bytes(cameras, history) + RECORD_ID_BYTES * history



@dataclass
class _Segment:
    """The watch of one (recipe, calibration) and what the report needs besides it."""

    recipe: str
    calibration_id: str | None
    calibration_hash: str | None
    watch: DriftWatch
    first_at: datetime
    records: int = 0
    # the record id of each of the watch's last ``history`` triggers (ring: trigger n at
    # n % history); their times are the watch's stamps
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    # per camera: (id, triggered_at, du, dv, statistic) of the last triggers
    trend: dict[tuple[int, str], deque[tuple[int, datetime, float, float, float]]] = field(
        default_factory=dict)


class DriftService:
    """The drift watch over one station's records (thread-safe; blocking: call off the loop)."""

    def __init__(
        self,
        store: Store,
        station: StationConfig | None,
        options: DriftOptions | None = None,
        *,
        window: int = 5_000,
        trend: int = 500,
    ) -> None:
        self.store = store
        self.station = station
        # the station file's drift history, the defaults otherwise
        self.options = options or DriftOptions(
            history=station.drift.history if station is not None else DriftOptions.history)
        # Records read at most on the first report (~0.05 ms each, their residuals only): they
        # should span the learning window and the drift of interest.
        self.window = window
        self.trend = trend
        self._lock = threading.Lock()
        self._last_id = 0
        self._segments: dict[tuple[str, str | None, str | None], _Segment] = {}
        self._current: _Segment | None = None
        self._responses: dict[str, Response] = {}  # by recipe name

    def prepare(self, recipe_name: str) -> None:
        """Build how each camera's move shows in the residuals of ``recipe_name`` now (~20 ms of
        Python on station 1), not on the read that meets its first record: the station's alarm
        watch does it before the station reports ready."""
        with self._lock:
            self._response(recipe_name)

    def report(self) -> DriftReport:
        """Read the records stored since the last call, run the watch, and report."""
        with self._lock:
            self._read_new()
            return self._report()

    def cameras(self) -> list[CameraDriftReport]:
        """Read the records stored since the last call, run the watch, and each camera's state
        without its trend: the station's alarm watch, whose round shares the station process
        with the trigger thread (a whole report builds ~2,000 trend points)."""
        with self._lock:
            self._read_new()
            seg = self._current
            return [] if seg is None else [self._camera(seg, d, trend=False)
                                           for d in seg.watch.states()]

    def _read_new(self) -> None:
        """Feed the watch the records with ids above the last one read (at most ``window``, the
        newest), in one query that parses only their residuals."""
        for rec in self.store.measurements.residuals_after(self._last_id, self.window):
            self._feed(rec)

    def _feed(self, rec: RecordResiduals) -> None:
        self._last_id = max(self._last_id, rec.id)
        if not rec.camera_residuals:
            return
        key = (rec.recipe, rec.calibration_id, rec.calibration_hash)
        seg = self._segments.get(key)
        if seg is None:
            seg = _Segment(rec.recipe, rec.calibration_id, rec.calibration_hash,
                           DriftWatch(self.options, self._response(rec.recipe)), rec.triggered_at,
                           ids=np.zeros(self.options.history, dtype=np.int64))
            self._segments[key] = seg
        self._current = seg
        seg.ids[seg.watch.triggers % len(seg.ids)] = rec.id
        means = {(c.view, c.camera_id): c.mean_px for c in rec.camera_residuals}
        in_fit = {(c.view, c.camera_id): c.used / c.count for c in rec.camera_residuals}
        seg.watch.update(means, rec.triggered_at.timestamp(), in_fit)
        stats = seg.watch.statistics()
        seg.records += 1
        for k, (du, dv) in means.items():
            points = seg.trend.setdefault(k, deque(maxlen=self.trend))
            points.append((rec.id, rec.triggered_at, du, dv, round(stats[k], 4)))

    def _response(self, recipe_name: str) -> Response:
        """How each camera's move shows in every camera's residuals (none without the station),
        built once per recipe."""
        if recipe_name not in self._responses:
            self._responses[recipe_name] = self._build_response(recipe_name)
        return self._responses[recipe_name]

    def _build_response(self, recipe_name: str) -> Response:
        if self.station is None:
            return {}
        recipe = next((r for r in self.station.recipes if r.name == recipe_name), None)
        if recipe is None:
            try:
                _, content = self.store.versions.content("recipe", recipe_name)
                recipe = RecipeConfig.model_validate(content)
            except Exception:  # a recipe the station file does not know: no attribution
                return {}
        try:
            return shift_response(self.station, recipe)
        except ValueError:  # e.g. a layout whose taught pose does not fix the pose
            return {}

    def _report(self) -> DriftReport:
        o = self.options
        rule = DriftRule(k=o.k, h_warn=o.h_warn, h_alarm=o.h_alarm, warmup=o.warmup,
                         arl0_warn=siegmund_arl(0.0, o.k, o.h_warn),
                         arl0_alarm=siegmund_arl(0.0, o.k, o.h_alarm))
        seg = self._current
        station = self.store.station
        last_verify = self._last_verify()
        if seg is None:
            return DriftReport(station=station, status="learning", records=0, messages=[],
                               rule=rule, cameras=[], last_id=self._last_id or None,
                               last_verify=last_verify)
        cams = [self._camera(seg, d) for d in seg.watch.states()]
        status: Status = max((c.status for c in cams), key=_RANK.__getitem__, default="learning")
        return DriftReport(
            station=station,
            status=status,
            recipe=seg.recipe,
            calibration_id=seg.calibration_id,
            calibration_hash=seg.calibration_hash,
            calibration_since=seg.first_at,
            last_id=self._last_id or None,
            records=seg.records,
            messages=[c.message for c in cams if c.status in ("warning", "alarm")],
            rule=rule,
            cameras=cams,
            last_verify=last_verify,
        )

    def _last_verify(self) -> LastVerify | None:
        found, _ = self.store.measurements.page(MeasurementFilter(part_id=VERIFY_PART_ID),
                                                None, 1)
        if not found:
            return None
        m = found[0]
        passed: bool | None
        try:
            report = verify_reference(self.store, m.id)
            passed, message = report.passed, report.message
        except (ConflictError, NotFoundError) as err:
            passed, message = None, str(err)
        return LastVerify(measurement_id=m.id, result_id=m.seq,
                          triggered_at=m.record.triggered_at, passed=passed, message=message)

    def _camera(self, seg: _Segment, d: CameraDrift, trend: bool = True
                ) -> CameraDriftReport:
        since_id = since = None
        n, i = seg.watch.triggers, d.since_trigger
        if i is not None and n - len(seg.ids) <= i < n and d.since is not None:
            # the record's time (stored in UTC) is the watch's stamp: exact to the microsecond
            since_id, since = int(seg.ids[i % len(seg.ids)]), datetime.fromtimestamp(d.since, UTC)
        return CameraDriftReport(
            view=d.view,
            camera_id=d.camera_id,
            status=d.status,
            message=drift_message(d, _clock(since) if since else None),
            statistic=round(d.statistic, 4),
            moved_camera=d.moved[1] if d.moved else None,
            moved_view=d.moved[0] if d.moved else None,
            shift_px=d.shift_norm_px,
            shift_uv_px=d.shift_px,
            residual_shift_px=d.residual_shift_px,
            since=since,
            since_id=since_id,
            triggers=0 if d.status == "learning" else d.triggers,
            learning_left=self.options.warmup - d.triggers if d.status == "learning" else 0,
            baseline_mean_px=d.mean_px,
            baseline_sigma_px=d.sigma_px,
            trend=[DriftPoint.model_construct(id=i, triggered_at=t, du_px=du, dv_px=dv,
                                              statistic=st)
                   for i, t, du, dv, st in (seg.trend.get(d.key, ()) if trend else ())],
        )


def _clock(t: datetime) -> str:
    """08:12 for today in the server's zone, with the date when it is older than a day."""
    local = t.astimezone()
    recent = datetime.now(UTC) - t < timedelta(hours=20)
    return local.strftime("%H:%M" if recent else "%Y-%m-%d %H:%M")


# ----------------------------------------------------------------------------- verify

#: the part id of a calibration verify's record (server.station.verifying)
VERIFY_PART_ID = "VERIFY"


def verify_reference(store: Store, measurement_id: int) -> VerifyReport:
    """Judge a stored measurement of the taught reference part against the active recipe's
    taught pose (:func:`judge_reference`)."""
    stored = store.measurements.get(measurement_id)
    info, content = store.versions.content("recipe", stored.record.recipe)
    recipe = RecipeConfig.model_validate(content)
    return judge_reference(stored.record, recipe, info.version, measurement_id, stored.seq)


def judge_reference(rec: MeasurementRecord, recipe: RecipeConfig, version: int,
                    measurement_id: int | None, result_id: int | None) -> VerifyReport:
    """Judge a measurement of the taught reference part against ``recipe``'s taught pose.

    Passes when the implied offset at the grasp point is within the recipe's grasp tolerances
    (``translation_mm``, ``rotation_deg``): a re-measured reference part should be at ~zero.
    """
    which = (f"measurement {measurement_id}" if measurement_id is not None
             else f"result {result_id}")
    if rec.T_rf_from_pf is None:
        raise ConflictError(
            f"{which} has no pose ({rec.reason}: {rec.message or 'no pose'});"
            " measure the reference part again"
        )
    off = frame_offsets(np.asarray(rec.T_rf_from_pf), recipe.T_rf_from_pf0.matrix,
                        recipe.T_pf_from_grasp.matrix, recipe.robot_convention)
    tol = recipe.tolerances
    mm, deg = off.grasp_displacement_mm, off.rotation_deg
    passed = mm <= tol.translation_mm and deg <= tol.rotation_deg
    verdict = "pass" if passed else "FAIL"
    message = (
        f"reference part of {rec.recipe} ({which}) lies {mm:.3f} mm and "
        f"{deg:.3f}° from its taught place (limits {tol.translation_mm:g} mm, "
        f"{tol.rotation_deg:g}°): {verdict}"
    )
    if not passed:
        over = [f"{mm - tol.translation_mm:.3f} mm" if mm > tol.translation_mm else "",
                f"{deg - tol.rotation_deg:.3f}°" if deg > tol.rotation_deg else ""]
        message += f" by {' and '.join(x for x in over if x)}"
    return VerifyReport(
        measurement_id=measurement_id,
        result_id=result_id,
        recipe=rec.recipe,
        recipe_version=version,
        measured_with_version=rec.recipe_version,
        measurement_result=rec.result,
        measurement_reason=rec.reason,
        passed=passed,
        offset=Offset(convention=off.convention, values=[float(v) for v in off.base]),
        grasp_displacement_mm=mm,
        rotation_deg=deg,
        limit_mm=tol.translation_mm,
        limit_deg=tol.rotation_deg,
        margin_mm=tol.translation_mm - mm,
        margin_deg=tol.rotation_deg - deg,
        message=message,
    )
