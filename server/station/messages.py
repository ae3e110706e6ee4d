"""The control channel's messages: each operation's request and answer, defined once.

The station process (server.station.control) validates a request into its model and
serialises the answer from its model; the API process (server.station.client) builds the
request from its model and parses the answer into its model, so mypy checks both ends against
the same types. How they travel (JSON lines over a Unix socket) is control.py's alone.

Every request is a model with its operation's name (``op``) and its answer's model
(``answer``); :data:`REQUESTS` finds the request model by name. Names and values are checked
strictly (``extra="forbid"``, no ``"5"`` for 5, no empty names), so a malformed request is
refused naming the argument.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, ClassVar, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PlainSerializer,
    PlainValidator,
    StrictFloat,
    StrictInt,
    StrictStr,
)

from drivers.links.result import ResultEvent
from server.drift import VerifyReport
from server.store.schemas import MeasurementRecord

Name = Annotated[StrictStr, Field(min_length=1, max_length=200)]


def _event(value: Any) -> ResultEvent:
    if isinstance(value, ResultEvent):
        return value
    if not isinstance(value, Mapping):
        raise ValueError(f"expected a result event object, got {type(value).__name__}")
    return ResultEvent.from_dict(value)  # ValueError naming the field that does not fit


#: a result event in a message: ResultEvent.to_dict's shape on the wire
Event = Annotated[ResultEvent, PlainValidator(_event),
                  PlainSerializer(lambda e: e.to_dict(), return_type=dict)]


class Message(BaseModel):
    """A request's arguments or an answer: unknown names are an error, not dropped."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class Request(Message):
    op: ClassVar[str]
    answer: ClassVar[type[Message]]


# ---------------------------------------------------------------------- answers


class PingAnswer(Message):
    pid: int
    station: str


class Readiness(Message):
    """The station's own readiness checks (the client adds ``station``: it answered)."""

    cameras: bool
    links: bool
    recipe: bool


class RecipeStatus(Message):
    name: str
    version: int
    number: int
    sha256: str
    convention: str


class CalibrationStatus(Message):
    id: str
    sha256: str
    version: int | None


class StationStatus(Message):
    """The station's live status. More parts (``mqtt``: the plant publisher, ``cpu``: the
    trigger path's scheduling) are added by name by whoever runs them: :meth:`part`."""

    model_config = ConfigDict(extra="allow", frozen=True)

    station: str
    state: str
    pid: int
    started_at: str | None
    deadline_ms: float
    recipe: RecipeStatus | None
    calibration: CalibrationStatus | None
    teach_armed: bool
    cameras: dict[str, str]
    links: dict[str, dict[str, Any]]
    plc: dict[str, Any]
    counts: dict[str, int]
    sequence_views: list[int]
    # the last recorded answer, as the listeners hear of it
    last_result: dict[str, Any] | None
    warm_up_ms: dict[str, float]
    store: dict[str, Any] | None
    archive: dict[str, Any] | None

    def part(self, name: str) -> dict[str, Any] | None:
        """A part added by name (e.g. ``mqtt``), None if the station has none by that name."""
        value = (self.model_extra or {}).get(name)
        return value if isinstance(value, dict) else None


class TriggerAnswer(Message):
    """One trigger's answer as the station gave it: the link's outcome, the station's message,
    the record and its result event."""

    result_code: int
    result_id: int
    final: bool
    views_done: int
    processing_ms: float
    offset: list[float] | None
    sigma_trans_mm: float
    sigma_rot_deg: float
    message: str
    measurement_id: int | None
    record: MeasurementRecord | None
    event: Event | None  # the recorded answer as every outlet shows it (None: not recorded)


class VerifyAnswer(Message):
    """A calibration verify as the station gave it: the code (0: judged, the report says how),
    the verify record's result id, the message, and the report (None: no verdict)."""

    result_code: int
    result_id: int
    message: str
    report: VerifyReport | None


class HandEyeAnswer(Message):
    """A hand-eye session's step as the station answered it (drivers.links.base.HandEyeOutcome)
    and the session as it is now (server.station.handeye.HandEye.status)."""

    code: int
    poses: int
    pose: int
    version: int
    sigma_mm: float
    sigma_deg: float
    holdout_rms_px: float
    holdout_mm: float
    holdout_deg: float
    message: str
    session: dict[str, Any]


class ArmTeachAnswer(Message):
    armed: bool
    recipe: str


class RecipeAnswer(Message):
    """A recipe version as the station now measures with it."""

    name: str
    version: int
    number: int
    sha256: str
    T_rf_from_pf0: dict[str, Any]


class ReloadAnswer(Message):
    changed: bool


class MetricsAnswer(Message):
    """The station process's Prometheus text (server.metrics.exposition)."""

    text: str


class MovePartAnswer(Message):
    """Where a rehearsal put the simulated part."""

    recipe: str
    recipe_version: int
    convention: str
    offset: list[float]
    T_rf_from_pf: list[list[float]]


class CameraViewFrame(Message):
    """One camera's newest frame for the live camera view, with its focus and light figures
    (mvpose_core.image_figures). ``note`` says why the frame is not new (a trigger came first,
    the camera is down or hardware-triggered); the figures are those of the frame shown."""

    camera_id: str
    jpeg_base64: str | None  # the downscaled frame as JPEG; None: none grabbed yet
    width: int  # of the downscaled frame (0 without one)
    height: int
    grabbed_at: str | None  # UTC, ISO 8601
    focus: float | None  # variance of the Laplacian, grey levels²
    focus_area: str  # "mark windows" or "whole image"
    mean: float | None  # mean grey level 0-255
    saturated_pct: float | None  # pixels at 255, %
    dark_pct: float | None  # pixels at 0, %
    note: str


class CameraViewAnswer(Message):
    """The live camera view's newest frame set: ``seq`` grows with every set grabbed."""

    seq: int
    period_s: float  # the station grabs at most one set per period
    cameras: list[CameraViewFrame]
    note: str


class ErrorBody(Message):
    """Why an operation failed: ``kind`` is not_found, invalid, conflict, busy or internal."""

    kind: str
    message: str


# ---------------------------------------------------------------------- requests


class PingRequest(Request):
    op = "ping"
    answer = PingAnswer


class StatusRequest(Request):
    op = "status"
    answer = StationStatus


class ReadinessRequest(Request):
    op = "readiness"
    answer = Readiness


class TriggerRequest(Request):
    """A commissioning trigger, measured as a link's would be."""

    op = "trigger"
    answer = TriggerAnswer

    part_id: StrictStr | None = Field(None, max_length=40)
    view: StrictInt = Field(0, ge=0, le=255)
    trigger_id: StrictInt | None = Field(None, ge=0, le=2**32 - 1)


class ArmTeachRequest(Request):
    op = "arm_teach"
    answer = ArmTeachAnswer

    by: Name


class VerifyRequest(Request):
    """Measure the taught reference part now and judge it (server.station.verifying)."""

    op = "verify"
    answer = VerifyAnswer

    by: Name


class HandEyeRequest(Request):
    """A step of the robot-driven hand-eye session (server.station.handeye)."""

    op = "handeye"
    answer = HandEyeAnswer

    step: Literal["begin", "pose", "calculate", "status"]
    by: Name
    holdout: int | None = Field(None, ge=0, le=50)
    robot_pose: list[float] | None = Field(None, min_length=6, max_length=7)


class TeachRequest(Request):
    op = "teach"
    answer = RecipeAnswer

    measurement_id: StrictInt = Field(ge=1)
    by: Name


class ActivateRecipeRequest(Request):
    op = "activate_recipe"
    answer = RecipeAnswer

    name: Name
    version: StrictInt | None = Field(None, ge=1)
    by: Name


class ReloadRecipesRequest(Request):
    op = "reload_recipes"
    answer = ReloadAnswer


class MetricsRequest(Request):
    op = "metrics"
    answer = MetricsAnswer


class MovePartRequest(Request):
    """A rehearsal on simulated cameras: the part at ``offset`` from the active reference, in
    the recipe's robot convention."""

    op = "move_part"
    answer = MovePartAnswer

    offset: list[Annotated[StrictFloat, Field(allow_inf_nan=False)]] = Field(
        min_length=1, max_length=16)


class CameraViewRequest(Request):
    """The live camera view's frames: grabbed between triggers when the newest set is older
    than the station's period (at most 2 per second), else the newest set again."""

    op = "camera_view"
    answer = CameraViewAnswer

    width: StrictInt = Field(640, ge=160, le=1280)


#: every operation's request model, by its name
REQUESTS: dict[str, type[Request]] = {r.op: r for r in (
    PingRequest, StatusRequest, ReadinessRequest, TriggerRequest, ArmTeachRequest, TeachRequest,
    ActivateRecipeRequest, ReloadRecipesRequest, MetricsRequest, MovePartRequest,
    VerifyRequest, HandEyeRequest, CameraViewRequest)}

__all__ = ["REQUESTS", "ActivateRecipeRequest", "ArmTeachAnswer", "ArmTeachRequest",
           "CalibrationStatus", "CameraViewAnswer", "CameraViewFrame", "CameraViewRequest",
           "ErrorBody", "HandEyeAnswer", "HandEyeRequest", "Message",
           "MetricsAnswer", "MetricsRequest",
           "MovePartAnswer", "MovePartRequest", "PingAnswer", "PingRequest", "Readiness",
           "ReadinessRequest", "RecipeAnswer", "RecipeStatus", "ReloadAnswer",
           "ReloadRecipesRequest", "Request", "StationStatus", "StatusRequest",
           "TeachRequest", "TriggerAnswer", "TriggerRequest", "VerifyAnswer", "VerifyRequest"]
