"""What the page draws over a frame: found marks, missing marks, their predicted search windows
and the reprojection residuals, all in full-resolution pixels of the camera.

Computed from the record and the station model the way the pipeline saw them: the recipe version
the record names (from the store), the station file's cameras at the taught view poses (records
do not keep a robot's reported flange pose), the detector's windows from mvpose_core's
prediction at the recipe's reference pose, and the reprojection of each mark at the record's
measured pose ``T_rf_from_pf`` (residual = detected − reprojected).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mvpose_core.detect import DetectOptions, predict_marks
from mvpose_core.scene import ViewCamera, project_recipe_marks, view_cameras
from mvpose_core.station import RecipeConfig, StationConfig
from server.store.schemas import MeasurementRecord

#: the detector options the pipeline uses for its windows (server.pipeline's default)
DETECT = DetectOptions(correct_perspective=True)


@dataclass(frozen=True)
class MarkOverlay:
    mark_id: str
    found: bool
    uv: tuple[float, float] | None  # detected centre (distorted px)
    reprojected: tuple[float, float] | None  # at the measured pose, or None without one
    predicted: tuple[float, float] | None  # at the recipe's reference pose (window centre)
    window: tuple[float, float, float, float] | None  # u0, v0, u1, v1 searched for this mark
    reason: str | None

    @property
    def residual(self) -> tuple[float, float] | None:
        if self.uv is None or self.reprojected is None:
            return None
        return (self.uv[0] - self.reprojected[0], self.uv[1] - self.reprojected[1])


@dataclass(frozen=True)
class CameraOverlay:
    view: int
    camera_id: str
    width: int
    height: int
    marks: tuple[MarkOverlay, ...]

    @property
    def residuals(self) -> list[tuple[float, float]]:
        return [r for m in self.marks if (r := m.residual) is not None]

    @property
    def rms_px(self) -> float | None:
        res = self.residuals
        if not res:
            return None
        return math.sqrt(sum(du * du + dv * dv for du, dv in res) / len(res))

    @property
    def mean_residual(self) -> tuple[float, float] | None:
        res = self.residuals
        if not res:
            return None
        return (sum(r[0] for r in res) / len(res), sum(r[1] for r in res) / len(res))


def recipe_from_content(name: str, version: int, content: dict[str, Any]) -> RecipeConfig:
    return RecipeConfig.model_validate({**content, "name": name, "version": version})


Window = tuple[tuple[float, float], tuple[float, float, float, float]]


class Geometry:
    """The station's view cameras and, per stored recipe version, each camera's windows.

    Stored recipe versions never change, so (name, version) keys the cache."""

    def __init__(self, station: StationConfig | None) -> None:
        self.station = station
        self.cameras = ({(vc.view, vc.camera_id): vc for vc in view_cameras(station)}
                        if station is not None else {})
        self._windows: dict[tuple[str, int, int, str], dict[str, Window]] = {}

    def windows(self, cam: ViewCamera, recipe: RecipeConfig) -> dict[str, Window]:
        key = (recipe.name, recipe.version, cam.view, cam.camera_id)
        hit = self._windows.get(key)
        if hit is None:
            if len(self._windows) > 512:
                self._windows.clear()
            hit = self._windows[key] = _windows(cam, recipe)
        return hit

    def overlays(self, record: MeasurementRecord, recipe: RecipeConfig | None
                 ) -> list[CameraOverlay]:
        return overlays(record, self, recipe)


def _windows(cam: ViewCamera, recipe: RecipeConfig) -> dict[str, Window]:
    """Each sighted mark's predicted centre and search window (the recipe's whole tolerance,
    the detector's widest search), as in mvpose_core.detect.window."""
    out: dict[str, Window] = {}
    for p in predict_marks(cam, recipe, recipe.T_rf_from_pf0.matrix,
                           DETECT.size_tolerance, DETECT.shape_slack_deg):
        u, v = float(p.uv[0]), float(p.uv[1])
        half = p.max_shift_px + p.radius_range[1] + DETECT.window_extra_px
        W, H = cam.model.width, cam.model.height
        out[p.mark.mark_id] = ((u, v), (max(u - half, 0.0), max(v - half, 0.0),
                                        min(u + half, float(W)), min(v + half, float(H))))
    return out


def overlays(
    record: MeasurementRecord, geometry: Geometry, recipe: RecipeConfig | None
) -> list[CameraOverlay]:
    """One overlay per camera of the record, in the record's order of detections."""
    cams = geometry.cameras
    T = np.array(record.T_rf_from_pf, dtype=float) if record.T_rf_from_pf is not None else None
    out = []
    for cd in record.detections:
        cam = cams.get((cd.view, cd.camera_id))
        windows = geometry.windows(cam, recipe) if cam is not None and recipe is not None else {}
        reproj: dict[str, tuple[float, float]] = {}
        if cam is not None and recipe is not None and T is not None:
            reproj = {pm.mark_id: (float(pm.uv[0]), float(pm.uv[1]))
                      for pm in project_recipe_marks(cam, recipe, T)}
        marks = []
        for d in cd.detections:
            pred, win = windows.get(d.mark_id, (None, None))
            marks.append(MarkOverlay(
                mark_id=d.mark_id, found=d.found,
                uv=(float(d.uv[0]), float(d.uv[1])) if d.uv is not None else None,
                reprojected=reproj.get(d.mark_id),
                predicted=pred,
                window=win,
                reason=d.reason,
            ))
        W, H = (cam.model.width, cam.model.height) if cam is not None else (2048, 2048)
        out.append(CameraOverlay(view=cd.view, camera_id=cd.camera_id, width=W, height=H,
                                 marks=tuple(marks)))
    return out
