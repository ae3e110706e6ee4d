"""Measuring saved images with the station's own pipeline, no cameras and no deadline.

``mvpose measure`` (image folders) and ``mvpose replay`` (the image archive) both build an
:class:`OfflineStation`: the station's :class:`server.pipeline.Pipeline` detects each view's
frames (``detect_view``) and measures them (``conclude``), and the record is built as the
station builds it (:func:`server.station.records.result_record`). The station's ``deadline_ms``
is lifted (decoding PNGs and a busy machine would otherwise fail every trigger
DEADLINE_EXCEEDED); everything else — windows, robust rule, recorrection, gate — is the
station's. Results are written as a CSV that ``mvpose validate`` reads without options and as
the records' JSON.
"""

from __future__ import annotations

import csv
import io
import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, cast

import numpy as np

from drivers.cameras import CaptureGroup, DriverError, Frame
from mvpose_core.calibration.files import content_hash
from mvpose_core.measure import Measurement
from mvpose_core.station import RecipeConfig, StationConfig
from mvpose_core.transforms import Array
from server.pipeline import Pipeline, StationResult, ViewCapture
from server.recipes import ActiveRecipe
from server.station.records import Provenance, result_record
from server.store.schemas import MeasurementRecord

#: deadline given to the pipeline offline (ms): no trigger is ever late
NO_DEADLINE_MS = 1e12


class _NoCapture:
    """Stands in for the capture group: offline, frames come from files, never from cameras."""

    def grab_all(self, *_: Any, **__: Any) -> Any:
        raise DriverError("offline measurement has no cameras to capture from")


def software_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("mvpose")
    except PackageNotFoundError:
        return "unknown"


def active_recipe(station: StationConfig, recipe: RecipeConfig, version: int | None = None,
                  sha256: str | None = None) -> ActiveRecipe:
    """A recipe as the station would run it (its number is its place in the station file)."""
    number = next((i for i, r in enumerate(station.recipes, 1) if r.name == recipe.name), 1)
    return ActiveRecipe(recipe, version or recipe.version,
                        sha256 or content_hash(recipe.model_dump(mode="json")), number)


@dataclass(frozen=True)
class Outcome:
    """One trigger measured offline: its key, the station's verdict and the record."""

    key: str
    result: StationResult
    record: MeasurementRecord

    @property
    def measurement(self) -> Measurement | None:
        return self.result.measurement


class OfflineStation:
    """The station's pipeline fed frames instead of cameras."""

    def __init__(self, station: StationConfig, recipe: ActiveRecipe,
                 calibration: tuple[str, str] | None) -> None:
        self.station = station
        self.recipe = recipe
        self.provenance = Provenance(station.name, software_version(), calibration)
        lifted = station.model_copy(update={"deadline_ms": NO_DEADLINE_MS})
        self.pipeline = Pipeline(lifted, cast(CaptureGroup, _NoCapture()))

    def views(self) -> list[int]:
        """The views the recipe measures in, in order."""
        return sorted({s.view for s in self.recipe.config.sightings})

    def measure(
        self, key: str, trigger_id: int, frames: Mapping[tuple[int, str], Frame | DriverError],
        flange_poses: Mapping[int, Array] | None = None, triggered_at: datetime | None = None,
        part_id: str | None = None,
    ) -> Outcome:
        """Detect and measure one trigger: ``frames`` maps (view, camera id) to the camera's
        frame or the error that replaced it (a missing file fails that camera only)."""
        t0 = time.monotonic()
        captures = []
        for view in self.views():
            flange = (flange_poses or {}).get(view)
            cams = self.pipeline.view_cameras(view, flange)
            vcap = ViewCapture(view=view, trigger_id=trigger_id, flange_pose=flange, cameras=cams)
            grabbed: dict[str, object] = {
                cid: frames.get((view, cid), DriverError(f"camera {cid!r}: no frame"))
                for cid in cams
            }
            self.pipeline.detect_view(vcap, grabbed, self.recipe.config)
            captures.append(vcap)
        result = self.pipeline.conclude(t0=t0, recipe=self.recipe, views=captures)
        record = result_record(self.provenance, result, trigger_id=trigger_id,
                               part_id=part_id if part_id is not None else key,
                               triggered_at=triggered_at or datetime.now(UTC), recipe=self.recipe)
        return Outcome(key, result, record)

    def close(self) -> None:
        self.pipeline.close()


# ------------------------------------------------------------------------------- output


def result_columns(recipe: RecipeConfig, prefix: str = "") -> list[str]:
    labels = list(recipe.robot_convention.labels)
    return [f"{prefix}{c}" for c in (
        "result", "reason_code", "reason", *labels, "sigma_mm", "sigma_deg",
        "sigma_detector_mm", "sigma_detector_deg", "sigma_calibration_mm",
        "sigma_calibration_deg", "detector_noise_px", "rms_px", "max_px", "message")]


def result_values(o: Outcome) -> list[object]:
    """The row of one outcome under :func:`result_columns`. The offset is written for OK
    results only (a NOK pose is not valid), so ``mvpose validate`` counts a NOK as missing."""
    rec = o.record
    m = o.measurement
    n = o.record.offset.convention.size if o.record.offset else 6
    offset: list[object] = [float(x) for x in rec.offset.values] if (
        rec.offset and rec.result == "OK") else [""] * n
    u = m.uncertainty if m is not None else None
    sig: list[object] = [
        rec.uncertainty.sigma_mm if rec.uncertainty else "",
        rec.uncertainty.sigma_deg if rec.uncertainty else "",
        *((u.sigma_detector_trans_mm, u.sigma_detector_rot_deg, u.sigma_calibration_trans_mm,
           u.sigma_calibration_rot_deg, u.detector_noise_px) if u else ("",) * 5),
    ]
    res = rec.residuals
    return [rec.result, rec.reason_code, rec.reason, *offset, *sig,
            res.rms_px if res else "", res.max_px if res else "", rec.message or ""]


def write_results(out: Path, recipe: RecipeConfig, outcomes: Sequence[Outcome],
                  stem: str = "measurements") -> tuple[Path, Path]:
    """``<stem>.csv`` (key, trigger_id, part_id, then :func:`result_columns`) and
    ``<stem>.json`` (the records, in the same order)."""
    out.mkdir(parents=True, exist_ok=True)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["key", "trigger_id", "part_id", *result_columns(recipe)])
    for o in outcomes:
        w.writerow([o.key, o.record.trigger_id, o.record.part_id or "", *result_values(o)])
    csv_path = out / f"{stem}.csv"
    csv_path.write_text(buf.getvalue(), encoding="utf-8")
    json_path = out / f"{stem}.json"
    json_path.write_text(json.dumps([o.record.model_dump(mode="json") for o in outcomes],
                                    indent=1) + "\n", encoding="utf-8")
    return csv_path, json_path


def summary(outcomes: Sequence[Outcome]) -> str:
    """One line: how many OK, and the NOK reasons with their counts."""
    ok = sum(o.record.result == "OK" for o in outcomes)
    reasons: dict[str, int] = {}
    for o in outcomes:
        if o.record.result != "OK":
            reasons[o.record.reason] = reasons.get(o.record.reason, 0) + 1
    nok = ", ".join(f"{k} {v}" for k, v in sorted(reasons.items()))
    return f"{len(outcomes)} triggers: {ok} OK, {len(outcomes) - ok} NOK" + (
        f" ({nok})" if nok else "")


def grasp_difference(a: Any, b: Any, recipe: RecipeConfig) -> tuple[float, float]:
    """Rotation (deg) and translation (mm) between two part poses, at the grasp frame."""
    from mvpose_core.transforms import transform_error

    G = recipe.T_pf_from_grasp.matrix
    return transform_error(np.asarray(a, dtype=float) @ G, np.asarray(b, dtype=float) @ G)
