"""Plausible measurement records for the store and API tests (random, from a seeded Generator)."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np

from mvpose_core.reasons import Reason
from mvpose_core.synth import random_displacement
from mvpose_core.transforms import RobotConvention, to_robot
from server.store.schemas import (
    CameraDetections,
    Detection,
    ImageRef,
    MeasurementRecord,
    Offset,
    Residuals,
    Uncertainty,
)

T0 = datetime(2026, 11, 2, 6, 0, tzinfo=UTC)
CAMERAS = ("cam1", "cam2", "cam3", "cam4")


def make_record(
    rng: np.random.Generator,
    station: str = "station1",
    *,
    trigger_id: int = 1,
    reason: Reason = Reason.OK,
    part_id: str | None = None,
    recipe: str = "floor_panel",
    recipe_version: int = 1,
    triggered_at: datetime | None = None,
    images: list[ImageRef] | None = None,
) -> MeasurementRecord:
    ok = reason == Reason.OK
    delta = random_displacement(rng, 20.0, 2.0)
    dets = []
    for i, cam in enumerate(CAMERAS):
        marks = []
        for j in range(2):
            found = ok or (i, j) != (0, 0)
            marks.append(Detection(
                mark_id=f"m{2 * i + j + 1}", found=found,
                uv=(float(rng.uniform(0, 2048)), float(rng.uniform(0, 2048))) if found else None,
                reason=None if found else "low contrast",
                quality={"contrast": float(rng.uniform(40, 120)),
                         "fit_residual_px": float(rng.uniform(0.01, 0.1))},
            ))
        dets.append(CameraDetections(view=1, camera_id=cam, detections=marks))
    stages = {"capture": rng.uniform(5, 9), "detect": rng.uniform(1, 3),
              "measure": rng.uniform(0.3, 1.0)}
    stages["total"] = sum(stages.values()) + 0.5
    return MeasurementRecord(
        station=station,
        trigger_id=trigger_id,
        part_id=part_id if part_id is not None else f"VIN{trigger_id:06d}",
        triggered_at=triggered_at or T0 + timedelta(seconds=30 * trigger_id),
        recipe=recipe,
        recipe_version=recipe_version,
        calibration_id="cal-2026-11-01",
        calibration_hash="ab" * 32,
        software_version="0.1.0",
        **MeasurementRecord.reason_fields(reason),
        message=None if ok else f"{reason.name.lower()} (test)",
        detections=dets,
        T_rf_from_pf=MeasurementRecord.matrix(delta) if ok else None,
        offset=Offset(convention=RobotConvention.FANUC,
                      values=[float(v) for v in to_robot(delta, RobotConvention.FANUC)])
        if ok else None,
        uncertainty=Uncertainty(sigma_mm=float(rng.uniform(0.2, 0.6)),
                                sigma_deg=float(rng.uniform(0.01, 0.05))) if ok else None,
        residuals=Residuals(rms_px=float(rng.uniform(0.05, 0.2)),
                            max_px=float(rng.uniform(0.2, 0.5))),
        timings_ms={k: round(float(v), 3) for k, v in stages.items()},
        images=images or [],
    )
