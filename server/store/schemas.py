"""The measurement record (one per trigger) as the pipeline fills it in, and what is stored."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from enum import IntEnum
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import AwareDatetime, BaseModel, ConfigDict, Field, computed_field, model_validator

from mvpose_core.transforms import RobotConvention

Name = Annotated[str, Field(min_length=1, max_length=64)]
Hash = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]
MAX_ID = 2**63 - 1  # BIGINT: ids and counters beyond it are refused at the edge


class _Model(BaseModel):
    # NaN and inf are not JSON, and the chain hashes canonical JSON: refuse them at the edge.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Detection(_Model):
    """One expected mark in one image: where it was found, or why not."""

    mark_id: Name
    found: bool
    uv: tuple[float, float] | None = Field(None, description="corrected centre, distorted px")
    reason: str | None = Field(None, max_length=200, description="why not found / rejected")
    quality: dict[str, float] = Field(
        default_factory=dict, description="e.g. contrast, fit_residual_px, axis_ratio"
    )

    @model_validator(mode="after")
    def _check(self) -> Detection:
        if self.found and self.uv is None:
            raise ValueError(f"mark {self.mark_id!r}: found but no uv")
        return self


class CameraDetections(_Model):
    view: int = Field(ge=1, le=255)
    camera_id: Name
    detections: list[Detection]


class Offset(_Model):
    """The frame offset in the recipe's robot convention (as the robot program reads it)."""

    convention: RobotConvention
    values: list[float]

    @model_validator(mode="after")
    def _check(self) -> Offset:
        if len(self.values) != self.convention.size:
            raise ValueError(
                f"a {self.convention.value} offset has {self.convention.size} values, "
                f"got {len(self.values)}"
            )
        return self


class Uncertainty(_Model):
    """1σ of the result at the grasp point: the total, and (records since the uncertainty
    model, docs/engine.md) its detector and calibration parts."""

    sigma_mm: float = Field(ge=0)
    sigma_deg: float = Field(ge=0)
    detector_mm: float | None = Field(None, ge=0)
    detector_deg: float | None = Field(None, ge=0)
    calibration_mm: float | None = Field(None, ge=0)
    calibration_deg: float | None = Field(None, ge=0)
    detector_noise_px: float | None = Field(None, ge=0, description="estimated from the residuals")


class Residuals(_Model):
    rms_px: float = Field(ge=0)
    max_px: float = Field(ge=0)


Matrix4 = Annotated[
    list[Annotated[list[float], Field(min_length=4, max_length=4)]],
    Field(min_length=4, max_length=4),
]


class SetAside(_Model):
    """An observation the robust rule left out of the pose (``candidate`` 0), or whose best
    candidate it replaced by the ``candidate``-th next one; and why (docs/engine.md)."""

    view: int = Field(ge=1, le=255)
    camera_id: Name
    mark_id: Name
    candidate: int = Field(0, ge=0, le=255)
    reason: str = Field(max_length=200)


class FlangePose(_Model):
    """The robot's actual flange pose a view was taken at (robot-mounted rigs)."""

    view: int = Field(ge=1, le=255)
    T_rf_from_gf: Matrix4


class CameraResidual(_Model):
    """One camera's reprojection residuals in one trigger: the drift watch's input."""

    view: int = Field(ge=1, le=255)
    camera_id: Name
    mean_px: tuple[float, float] = Field(description="mean (du, dv), observed − predicted, px")
    rms_px: float = Field(ge=0)
    count: int = Field(ge=1, le=65535, description="observations of this camera")
    used: int = Field(ge=0, le=65535, description="of them in the pose fit")


@dataclass(frozen=True)
class RecordResiduals:
    """What the drift watch reads of one stored record (MeasurementRepository.residuals_after)."""

    id: int
    recipe: str
    triggered_at: datetime
    calibration_id: str | None
    calibration_hash: str | None
    camera_residuals: list[CameraResidual]


class ImageRef(_Model):
    """An archived frame, by path relative to the image archive root."""

    view: int = Field(ge=1, le=255)
    camera_id: Name
    path: str = Field(min_length=1, max_length=400)




class MeasurementRecord(_Model):
    """Everything one trigger produced; written before the PLC sees RESULT_VALID.

    ``result`` is "OK" exactly when ``reason_code`` is 0 (mvpose_core.gate.Reason.OK); the
    reason is stored as the int the PLC receives and its name, so that the record stays readable
    when codes are added later. An OK record carries a pose and an offset.
    """

    station: Name
    trigger_id: int = Field(ge=0, le=MAX_ID, description="the PLC's trigger counter")
    part_id: str | None = Field(None, max_length=64)
    triggered_at: AwareDatetime
    recipe: Name
    recipe_version: int = Field(ge=1, le=2**31 - 1)
    calibration_id: str | None = Field(None, max_length=64)
    calibration_hash: Hash | None = None
    software_version: str = Field(min_length=1, max_length=64)
    result: Literal["OK", "NOK"]
    reason_code: int = Field(ge=0, le=65535)
    reason: Name
    message: str | None = Field(None, max_length=500, description="the gate's one-line why")
    detections: list[CameraDetections] = Field(default_factory=list)
    T_rf_from_pf: Matrix4 | None = Field(None, description="measured part pose, 4x4, mm")
    offset: Offset | None = None
    uncertainty: Uncertainty | None = None
    residuals: Residuals | None = None
    timings_ms: dict[str, float] = Field(default_factory=dict, description="stage -> ms")
    images: list[ImageRef] = Field(default_factory=list)
    camera_residuals: list[CameraResidual] | None = Field(
        None, description="per camera of the pose fit; absent in records before the drift watch"
    )
    pose_valid: bool | None = Field(
        None, description="the pose may be used (OK); a NOK record keeps its pose for diagnosis "
        "only. Absent in older records: there, an OK result")
    set_aside: list[SetAside] | None = Field(
        None, description="observations the robust rule dropped or replaced, and why")
    flange_poses: list[FlangePose] | None = Field(
        None, description="the robot's actual flange pose of each view that sent one")

    @model_validator(mode="after")
    def _check(self) -> MeasurementRecord:
        if (self.result == "OK") != (self.reason_code == 0):
            raise ValueError(
                f"result {self.result!r} does not agree with reason_code {self.reason_code}"
            )
        if self.result == "OK" and (self.T_rf_from_pf is None or self.offset is None):
            raise ValueError("an OK record needs T_rf_from_pf and offset")
        if any(v < 0 for v in self.timings_ms.values()):
            raise ValueError(f"stage timings must be >= 0 ms, got {self.timings_ms}")
        return self

    @staticmethod
    def reason_fields(code: IntEnum) -> dict[str, Any]:
        """``result``, ``reason_code`` and ``reason`` from a Reason member."""
        return {
            "result": "OK" if int(code) == 0 else "NOK",
            "reason_code": int(code),
            "reason": code.name,
        }

    @staticmethod
    def matrix(T: np.ndarray) -> list[list[float]]:
        """A 4x4 numpy transform as the nested list the record stores."""
        T = np.asarray(T, dtype=float)
        if T.shape != (4, 4):
            raise ValueError(f"T_rf_from_pf must be 4x4, got shape {T.shape}")
        return [[float(x) for x in row] for row in T]


def _drop_result_id(data: Any) -> Any:
    """What this model wrote reads back: ``result_id`` (computed, = seq) is checked, not kept."""
    if isinstance(data, dict) and "result_id" in data:
        data = dict(data)
        result_id = data.pop("result_id")
        if result_id != data.get("seq"):
            raise ValueError(f"result_id {result_id!r} is not seq {data.get('seq')!r}")
    return data


class StoredMeasurement(_Model):
    """A record as stored: its place in the chain and the hashes that seal it."""

    id: int
    seq: int
    stored_at: datetime
    prev_hash: Hash
    hash: Hash
    record: MeasurementRecord

    @computed_field(description="the result id the PLC read for this trigger (= seq)")  # type: ignore[prop-decorator]
    @property
    def result_id(self) -> int:
        return self.seq

    _read_back = model_validator(mode="before")(_drop_result_id)


class MeasurementSummary(_Model):
    """A list or CSV row: the result without detections and images (ask for one for those)."""

    id: int
    seq: int
    stored_at: datetime
    triggered_at: datetime
    trigger_id: int
    part_id: str | None
    recipe: str
    recipe_version: int
    result: Literal["OK", "NOK"]
    reason_code: int
    reason: str
    message: str | None = None
    calibration_id: str | None = None
    calibration_hash: str | None = None
    offset: Offset | None = None
    uncertainty: Uncertainty | None = None
    residuals: Residuals | None = None
    timings_ms: dict[str, float] = Field(default_factory=dict)
    total_ms: float | None = Field(None, description="timings_ms['total'] when the pipeline set it")
    hash: str

    @computed_field(description="the result id the PLC read for this trigger (= seq)")  # type: ignore[prop-decorator]
    @property
    def result_id(self) -> int:
        return self.seq

    _read_back = model_validator(mode="before")(_drop_result_id)


class ImageStatus(_Model):
    view: int
    camera_id: str
    path: str
    state: Literal["stored", "evicted", "pending"]
    bytes: int | None = None


class MeasurementDetail(StoredMeasurement):
    """One measurement with its detections (inside ``record``) and the state of its images."""

    image_status: list[ImageStatus]


class ChainReport(_Model):
    ok: bool
    station: str
    checked: int
    head_seq: int | None
    head_hash: Hash | None
    first_bad_seq: int | None = None
    problem: str | None = None


class MeasurementFilter(_Model):
    """Filters of the measurement list and export; every field optional."""

    since: datetime | None = None
    until: datetime | None = None
    result: Literal["OK", "NOK"] | None = None
    reason_code: int | None = None
    recipe: str | None = None
    part_id: str | None = None
    result_id: int | None = Field(None, description="the result id the PLC read (= seq)")
    trigger_id: int | None = Field(None, description="the trigger id the link sent")
