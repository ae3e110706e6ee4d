"""What the trigger thread does around the pipeline: recipe, view, robot-mounted sequence, teach.

One :class:`TriggerRunner` per runtime, used only from the runtime's single ``trigger`` thread
(PLC and REST triggers alike), so the sequence of views and the teach request need no lock; the
last result is read by REST threads under a lock.
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import datetime

import numpy as np

from drivers.plc.codecs import plc_to_pose
from drivers.plc.seam import TriggerOutcome, TriggerRequest
from mvpose_core.reasons import Reason, reason_name
from mvpose_core.station import StationConfig
from mvpose_core.transforms import from_robot
from server.pipeline import Pipeline, TriggerResult, ViewCapture
from server.recipes import ActiveRecipe, RecipeBook
from server.state import Services
from server.store.schemas import MeasurementRecord

log = logging.getLogger(__name__)


@dataclass
class LastResult:
    trigger_id: int
    part_id: str | None
    recipe: str
    result: str
    reason_code: int
    reason: str
    message: str
    processing_ms: float
    measurement_id: int | None
    at: datetime


class TriggerRunner:
    """Runs one trigger at a time: resolves recipe and view, gathers views, records, teaches."""

    def __init__(self, station: StationConfig, pipeline: Pipeline, book: RecipeBook,
                 services: Services, archive_exec: ThreadPoolExecutor) -> None:
        self.station = station
        self.pipeline = pipeline
        self.book = book
        self.services = services
        self.archive_exec = archive_exec
        self.sequence: list[ViewCapture] = []  # views of a robot-mounted rig gathered so far
        self.teach_armed = False
        self.last: LastResult | None = None
        self.counts: dict[str, int] = {"triggers": 0, "ok": 0, "nok": 0, "views": 0}
        self._lock = threading.Lock()

    def run(self, req: TriggerRequest, t0: float, at: datetime) -> TriggerResult:
        self.counts["triggers"] += 1
        recipe = self.book.by_number(req.recipe) if req.recipe else self.book.selected
        if recipe is None:
            return self._reject(req, t0, at, self.book.selected, Reason.UNKNOWN_RECIPE,
                                f"recipe number {req.recipe} is not in the station file")
        views = sorted({s.view for s in recipe.config.sightings})
        view = req.view_index or (views[0] if len(views) == 1 else 0)
        if view not in views:
            self.sequence = []
            return self._reject(req, t0, at, recipe, Reason.UNKNOWN_VIEW,
                                f"view index {req.view_index} not among the recipe's views {views}")
        flange = None
        if req.robot_pose is not None and self.station.robot_mounted:
            conv = recipe.config.robot_convention
            flange = from_robot(plc_to_pose(req.robot_pose, conv), conv)
        vcap = self.pipeline.capture_view(view, req.trigger_id, recipe.config, flange, t0)
        if view == views[0]:
            self.sequence = []
        self.sequence = [v for v in self.sequence if v.view != view] + [vcap]
        if view != views[-1]:
            self.counts["views"] += 1
            return TriggerResult(
                outcome=TriggerOutcome(result_code=0, processing_ms=(time.monotonic() - t0) * 1e3,
                                       views_done=len(self.sequence), final=False),
                record=None, stored=None, measurement=None, frames={}, message="view done")
        seq, self.sequence = self.sequence, []
        result = self.pipeline.conclude(trigger_id=req.trigger_id, part_id=req.part_id or None,
                                        triggered_at=at, t0=t0, recipe=recipe, views=seq)
        self._after(result, recipe)
        return result

    def _reject(self, req: TriggerRequest, t0: float, at: datetime, recipe: ActiveRecipe | None,
                code: Reason, message: str) -> TriggerResult:
        """A trigger the pipeline cannot run: still one NOK record, and its code to the PLC."""
        rc = recipe or next(iter(self.book.recipes.values()))
        calib = self.pipeline.calibration
        record = MeasurementRecord(
            station=self.station.name, trigger_id=req.trigger_id, part_id=req.part_id or None,
            triggered_at=at, recipe=rc.config.name, recipe_version=rc.version,
            calibration_id=calib[0] if calib else None,
            calibration_hash=calib[1] if calib else None, T_rf_from_pf=None,
            software_version=self.services.software_version,
            result="NOK", reason_code=int(code), reason=code.name, message=message[:500],
            timings_ms={"total": (time.monotonic() - t0) * 1e3},
        )
        stored = self.services.record_measurement(record)
        result = TriggerResult(
            outcome=TriggerOutcome(result_code=int(code),
                                   processing_ms=(time.monotonic() - t0) * 1e3),
            record=record, stored=stored, measurement=None, frames={}, message=message)
        self._after(result, rc)
        return result

    def _after(self, result: TriggerResult, recipe: ActiveRecipe) -> None:
        rec, stored = result.record, result.stored
        assert rec is not None
        ok = rec.result == "OK"
        self.counts["ok" if ok else "nok"] += 1
        with self._lock:
            self.last = LastResult(
                trigger_id=rec.trigger_id, part_id=rec.part_id, recipe=rec.recipe,
                result=rec.result, reason_code=rec.reason_code,
                reason=reason_name(rec.reason_code), message=result.message,
                processing_ms=result.outcome.processing_ms,
                measurement_id=stored.id if stored else None, at=rec.triggered_at)
        if self.teach_armed and ok and rec.T_rf_from_pf is not None:
            self.teach_armed = False
            self.book.teach(recipe.config.name, np.array(rec.T_rf_from_pf), "plc",
                            f"taught by PLC command from trigger {rec.trigger_id}")
        if rec.images and stored is not None:
            self.archive_exec.submit(self._archive, stored.id, rec, result.frames)

    def _archive(self, measurement_id: int, rec: MeasurementRecord,
                 frames: dict[tuple[int, str], np.ndarray]) -> None:
        try:
            self.services.images.write(measurement_id, rec.images, rec.result == "OK", frames)
        except Exception:
            log.exception("measurement %d: archiving its frames failed", measurement_id)
