"""Sample data for the operator page's tests and screenshots: records the pose engine really
measured on a simulated station, with their frames rendered and archived.

Each record comes from mvpose_core end to end: a part displaced at random, its marks projected
into every camera with detector noise (``synthetic_observations``), the pose estimated and gated
(``measure``), and, for records that keep frames, the images rendered (``render_view``) with the
part where the estimate puts it. A MARKS_MISSING record loses one mark (occluded in its image).
Stored through :meth:`Services.record_measurement` and :meth:`ImageArchive.write`, as the
pipeline stores its own.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from datetime import UTC, datetime, timedelta

import numpy as np

from mvpose_core.measure import measure
from mvpose_core.reasons import Reason
from mvpose_core.render import RenderOptions, render_view
from mvpose_core.scene import view_cameras
from mvpose_core.station import RecipeConfig, StationConfig
from mvpose_core.synth import random_displacement, synthetic_observations
from mvpose_core.transforms import matrix_to_xyzwpr
from server.drift import record_camera_residuals
from server.state import Services
from server.store.schemas import (
    CameraDetections,
    Detection,
    MeasurementRecord,
    Offset,
    Residuals,
    StoredMeasurement,
    Uncertainty,
)

T0 = datetime(2026, 11, 2, 6, 0, tzinfo=UTC)


@dataclass
class SampleLine:
    """A simulated production line writing into one station's store."""

    services: Services
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(7))
    start: datetime = T0
    period_s: float = 30.0
    noise_px: float = 0.08
    trigger_id: int = 0

    @property
    def station(self) -> StationConfig:
        if self.services.station is None:
            raise ValueError("sample records need a station file (Settings.station)")
        return self.services.station

    def recipe(self) -> tuple[RecipeConfig, int]:
        """The active version of the station's default recipe (as seeded from the file)."""
        name = self.station.default_recipe or self.station.recipes[0].name
        info, content = self.services.store.versions.content("recipe", name)
        return RecipeConfig.model_validate({**content, "version": info.version}), info.version

    def record(self, *, missing: str | None = None, frames: bool = False,
               shift_px: tuple[float, float] = (0.0, 0.0), shift_camera: str | None = None,
               part_id: str | None = None) -> tuple[MeasurementRecord, dict[tuple[int, str],
                                                                              np.ndarray]]:
        """One measured record (and its rendered frames when ``frames``).

        ``missing`` names a mark that is not found; ``shift_px`` moves every observation of
        ``shift_camera`` (a camera that moved since calibration)."""
        self.trigger_id += 1
        recipe, version = self.recipe()
        station, rng = self.station, self.rng
        T_true = recipe.T_rf_from_pf0.matrix @ random_displacement(rng, 4.0, 0.4)
        obs = synthetic_observations(station, recipe, T_true, rng, self.noise_px)
        obs = [replace(o, uv=o.uv + np.asarray(shift_px)) if o.camera_id == shift_camera else o
               for o in obs]
        used = [o for o in obs if o.mark_id != missing]
        t0 = datetime.now(UTC)
        m = measure(station, recipe, used)
        solve_ms = (datetime.now(UTC) - t0).total_seconds() * 1e3
        reason = Reason.MARKS_MISSING if missing else m.gate.reason
        ok = reason == Reason.OK
        at = {(o.view, o.camera_id, o.mark_id): o.uv for o in used}
        dets = []
        for cam in view_cameras(station):
            marks = [o.mark_id for o in obs if (o.view, o.camera_id) == (cam.view, cam.camera_id)]
            if not marks:
                continue
            dets.append(CameraDetections(view=cam.view, camera_id=cam.camera_id, detections=[
                Detection(mark_id=mid, found=True,
                          uv=(float(at[key][0]), float(at[key][1])),
                          quality={"contrast": float(rng.uniform(90, 130))})
                if (key := (cam.view, cam.camera_id, mid)) in at else
                Detection(mark_id=mid, found=False, reason="nothing mark-like in window")
                for mid in marks]))
        res = np.asarray(m.pose.residuals_px)
        stages = {"capture": float(rng.uniform(6, 9)), "detect": float(rng.uniform(2, 4)),
                  "measure": solve_ms}
        stages["total"] = sum(stages.values()) + float(rng.uniform(0.3, 0.8))
        record = MeasurementRecord(
            station=self.services.station_name,
            trigger_id=self.trigger_id,
            part_id=part_id or f"VIN{self.trigger_id:06d}",
            triggered_at=self.start + timedelta(seconds=self.period_s * self.trigger_id),
            recipe=recipe.name, recipe_version=version,
            calibration_id=None, calibration_hash=None,
            software_version=self.services.software_version,
            **MeasurementRecord.reason_fields(reason),
            message=None if ok else (f"mark {missing} not found" if missing else m.gate.message),
            detections=dets,
            T_rf_from_pf=MeasurementRecord.matrix(m.T_rf_from_pf),
            offset=Offset(convention=m.convention, values=[float(v) for v in m.offset])
            if ok else None,
            uncertainty=Uncertainty(sigma_mm=m.sigma_trans_mm, sigma_deg=m.sigma_rot_deg),
            residuals=Residuals(rms_px=float(np.sqrt(np.mean(np.sum(res**2, axis=1)))),
                                max_px=float(np.max(np.linalg.norm(res, axis=1)))),
            timings_ms={k: round(v, 3) for k, v in stages.items()},
            camera_residuals=record_camera_residuals(used, m),
        )
        images: dict[tuple[int, str], np.ndarray] = {}
        if frames:
            opts = RenderOptions(supersample=4, occluded=(missing,) if missing else ())
            for cam in view_cameras(station):
                shown = render_view(cam, recipe, m.T_rf_from_pf, rng, opts)
                images[(cam.view, cam.camera_id)] = shown.image
        return record, images

    def store(self, record: MeasurementRecord,
              images: dict[tuple[int, str], np.ndarray]) -> StoredMeasurement:
        """Store the record (with image refs when it has frames), then write its frames."""
        archive = self.services.images
        if images:
            refs = [r for r in archive.plan(record.station, record.trigger_id, record.triggered_at,
                                            False, sorted(images))]
            record = record.model_copy(update={"images": refs})
        stored = self.services.record_measurement(record)
        if images:
            archive.write(stored.id, record.images, record.result == "OK", images)
        return stored

    def taught_version(self, stored: StoredMeasurement, by: str = "operator-1") -> int:
        """A new (inactive) recipe version whose reference is this record's pose, as a teach
        stores it; returns its number."""
        recipe, _ = self.recipe()
        if stored.record.T_rf_from_pf is None:
            raise ValueError(f"measurement {stored.id} has no pose to teach from")
        xyzwpr = matrix_to_xyzwpr(np.array(stored.record.T_rf_from_pf))
        content = recipe.model_dump(mode="json", exclude={"version"})
        content["T_rf_from_pf0"] = {"xyz": [float(v) for v in xyzwpr[:3]],
                                    "wpr": [float(v) for v in xyzwpr[3:]]}
        info = self.services.store.versions.add(
            "recipe", recipe.name, content, by, comment=f"taught from measurement {stored.id}")
        return info.version

    def run(self, n: int, *, missing_every: int = 0, frames_every: int = 0,
            **kw: object) -> list[StoredMeasurement]:
        """``n`` records; every ``missing_every``-th misses a mark, every ``frames_every``-th
        keeps its frames (0: never)."""
        out = []
        for k in range(1, n + 1):
            miss = "B2" if missing_every and k % missing_every == 0 else None
            keep = bool(frames_every and k % frames_every == 0)
            out.append(self.store(*self.record(missing=miss, frames=keep, **kw)))  # type: ignore[arg-type]
        return out
