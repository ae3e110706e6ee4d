"""The audit record of one answer, built in one place from what the station decided.

Every answer a link gives has a record with the same code: a measured result
(:func:`result_record`), a trigger the pipeline could not run (unknown recipe or view), or an
answer the link or the station's watchdog gave on its own (:func:`failure_record`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime

import numpy as np

from mvpose_core.detect import MarkDetection
from mvpose_core.reasons import reason_name
from server.drift import record_camera_residuals
from server.pipeline import StationResult
from server.recipes import ActiveRecipe
from server.store.schemas import (
    CameraDetections,
    Detection,
    FlangePose,
    ImageRef,
    MeasurementRecord,
    Offset,
    Residuals,
    SetAside,
    Uncertainty,
)


@dataclass(frozen=True)
class Provenance:
    """Which station, software and calibration a record comes from."""

    station: str
    software_version: str
    calibration: tuple[str, str] | None  # (id, sha256) of the active calibration


def result_record(prov: Provenance, result: StationResult, *, trigger_id: int,
                  part_id: str | None, triggered_at: datetime, recipe: ActiveRecipe,
                  images: Sequence[ImageRef] = ()) -> MeasurementRecord:
    """The record of a measured trigger (OK or NOK)."""
    rc = recipe.config
    meas = result.measurement
    dets = [
        CameraDetections(view=v.view, camera_id=cid, detections=[_detection(d) for d in ds])
        for v in result.views for cid, ds in v.detections.items()
    ]
    pose = offset = unc = res = cams = None
    aside: list[SetAside] | None = None
    if meas is not None:
        cams = record_camera_residuals(result.observations, meas)  # the drift watch's input
        aside = [SetAside(view=d.view, camera_id=d.camera_id, mark_id=d.mark_id,
                          reason=d.reason[:200]) for d in meas.dropped]
        aside += [SetAside(view=r.view, camera_id=r.camera_id, mark_id=r.mark_id,
                           candidate=r.candidate, reason=r.reason[:200]) for r in meas.replaced]
        pose = MeasurementRecord.matrix(meas.T_rf_from_pf)
        offset = Offset(convention=rc.robot_convention, values=[float(x) for x in meas.offset])
        parts = meas.uncertainty
        unc = Uncertainty(sigma_mm=float(meas.sigma_trans_mm), sigma_deg=float(meas.sigma_rot_deg))
        if parts is not None:  # the two parts of the 1σ (docs/engine.md, uncertainty model)
            unc = unc.model_copy(update={
                "detector_mm": _part(parts.sigma_detector_trans_mm),
                "detector_deg": _part(parts.sigma_detector_rot_deg),
                "calibration_mm": _part(parts.sigma_calibration_trans_mm),
                "calibration_deg": _part(parts.sigma_calibration_rot_deg),
                "detector_noise_px": _part(parts.detector_noise_px)})
        r = np.asarray(meas.pose.residuals_px, dtype=float).reshape(-1, 2)
        norms = np.linalg.norm(r, axis=1) if len(r) else np.zeros(1)
        res = Residuals(rms_px=float(np.sqrt(np.mean(norms**2))), max_px=float(norms.max()))
    return MeasurementRecord(
        station=prov.station, trigger_id=trigger_id, part_id=part_id or None,
        triggered_at=triggered_at, recipe=rc.name, recipe_version=recipe.version,
        calibration_id=prov.calibration[0] if prov.calibration else None,
        calibration_hash=prov.calibration[1] if prov.calibration else None,
        software_version=prov.software_version,
        result="OK" if result.code == 0 else "NOK", reason_code=result.code,
        reason=reason_name(result.code), message=result.message[:500] or None,
        detections=dets, T_rf_from_pf=pose, offset=offset, uncertainty=unc, residuals=res,
        camera_residuals=cams, pose_valid=result.code == 0, set_aside=aside or None,
        flange_poses=[FlangePose(view=v.view, T_rf_from_gf=MeasurementRecord.matrix(v.flange_pose))
                      for v in result.views if v.flange_pose is not None] or None,
        timings_ms={k: round(v, 4) for k, v in result.timings_ms.items()}, images=list(images),
    )


def failure_record(prov: Provenance, *, code: int, message: str, trigger_id: int,
                   part_id: str | None, triggered_at: datetime, recipe: ActiveRecipe,
                   total_ms: float) -> MeasurementRecord:
    """The record of an answer without a measurement: NOK with ``code``, no pose."""
    return MeasurementRecord(
        station=prov.station, trigger_id=trigger_id, part_id=part_id or None,
        triggered_at=triggered_at, recipe=recipe.config.name, recipe_version=recipe.version,
        calibration_id=prov.calibration[0] if prov.calibration else None,
        calibration_hash=prov.calibration[1] if prov.calibration else None,
        T_rf_from_pf=None, pose_valid=False, software_version=prov.software_version, result="NOK",
        reason_code=code, reason=reason_name(code), message=message[:500] or None,
        timings_ms={"total": round(total_ms, 4)},
    )


# math.isfinite, not numpy's: a record has some forty of these, and numpy's scalar call costs
# ~1 µs each warm and more on the trigger thread after detection.
def _part(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _detection(d: MarkDetection) -> Detection:
    quality = {k: float(v) for k, v in (("contrast", d.contrast), ("fit_residual_px",
               d.fit_residual_px), ("axis_ratio", d.axis_ratio), ("radius_px", d.radius_px))
               if _finite(v) is not None}
    uv = (float(d.uv[0]), float(d.uv[1])) if d.found and d.uv is not None else None
    return Detection(mark_id=d.mark_id, found=d.found and uv is not None, uv=uv,
                     reason=(d.reason or None) and d.reason[:200], quality=quality)
