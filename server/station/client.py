"""The API process's handle on the station process: the control channel's client.

Every call opens a connection, sends one request and reads one answer (a Unix socket on the
same machine: well under a millisecond), so a restarted station is reached again without any
reconnect logic. A station that does not answer is :class:`StationDownError`, which the API maps
to 503 and readiness reports as ``station: false``. Requests are built from, and answers parsed
into, the models of server.station.messages; the framing is server.station.control's.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from pydantic import ValidationError

from server.errors import (
    ConflictError,
    InvalidInputError,
    NotFoundError,
    NotReadyError,
    StationFailedError,
)
from server.station.control import ChannelError, read_answer, request_line
from server.station.messages import (
    ActivateRecipeRequest,
    ArmTeachAnswer,
    ArmTeachRequest,
    CameraViewAnswer,
    CameraViewRequest,
    HandEyeAnswer,
    HandEyeRequest,
    Message,
    MetricsAnswer,
    MetricsRequest,
    MovePartAnswer,
    MovePartRequest,
    PingAnswer,
    PingRequest,
    Readiness,
    ReadinessRequest,
    RecipeAnswer,
    ReloadAnswer,
    ReloadRecipesRequest,
    Request,
    StationStatus,
    StatusRequest,
    TeachRequest,
    TriggerAnswer,
    TriggerRequest,
    VerifyAnswer,
    VerifyRequest,
)

A = TypeVar("A", bound=Message)


class StationDownError(NotReadyError):
    """The station process does not answer on its control channel."""


_KINDS: dict[str, type[Exception]] = {
    "not_found": NotFoundError, "invalid": InvalidInputError, "conflict": ConflictError,
    "busy": ConflictError,
}


class StationClient:
    """Blocking calls to the station's control channel (from FastAPI's worker threads)."""

    def __init__(self, path: Path, timeout_s: float = 5.0, status_max_age_s: float = 0.25) -> None:
        self.path = Path(path)
        self.timeout_s = timeout_s
        # MES clients poll the status many times a second; each call would cost the station
        # process a request on its loop, beside the trigger thread (bench station: 0.27 -> 0.34
        # cores at 200 REST requests/s). One answer serves every request for this long.
        self.status_max_age_s = status_max_age_s
        self._status: tuple[float, StationStatus] | None = None
        self._status_lock = threading.Lock()

    def call(self, op: str, timeout_s: float | None = None, **args: Any) -> Any:
        """Operation ``op`` with ``args`` as JSON values; its result as JSON values (tools;
        the API uses the typed calls below)."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
                sock.settimeout(timeout)
                sock.connect(str(self.path))
                sock.sendall(request_line(op, args))
                data = b""
                while not data.endswith(b"\n"):
                    chunk = sock.recv(1 << 20)
                    if not chunk:
                        break
                    data += chunk
        except (FileNotFoundError, ConnectionRefusedError) as err:
            raise StationDownError(f"the station process is not running ({err.strerror})") \
                from None
        except TimeoutError:
            raise StationDownError(f"the station process did not answer {op!r} within "
                                   f"{timeout:g} s") from None
        except OSError as err:
            raise StationDownError(f"the station process is not reachable: {err}") from None
        if not data:
            raise StationDownError("the station process closed the control channel")
        try:
            return read_answer(data)
        except ChannelError as err:
            exc = _KINDS.get(err.kind)
            if exc is None:  # "internal" and any kind this client does not know
                raise StationFailedError(f"the station failed: {err.message}") from None
            raise exc(err.message) from None

    def ask(self, request: Request, answer: type[A], timeout_s: float | None = None) -> A:
        """``request`` to the station; its answer as ``answer`` (the request's answer model)."""
        if answer is not type(request).answer:
            raise TypeError(f"{request.op!r} is answered with {type(request).answer.__name__}, "
                            f"not {answer.__name__}")
        result = self.call(request.op, timeout_s, **request.model_dump(mode="json"))
        try:
            return answer.model_validate(result)
        except ValidationError as err:  # a station of another version: not this API's station
            raise StationDownError(f"the station's answer to {request.op!r} does not fit this "
                                   f"API ({err.error_count()} errors, first: "
                                   f"{err.errors()[0]['loc']}: {err.errors()[0]['msg']})") \
                from None

    # ------------------------------------------------------------------ what the API uses
    def ping(self, timeout_s: float | None = None) -> PingAnswer:
        return self.ask(PingRequest(), PingAnswer, timeout_s)

    def status(self) -> StationStatus:
        """The station's status, at most ``status_max_age_s`` old."""
        with self._status_lock:  # one caller asks the station; the others wait for its answer
            now = time.monotonic()
            if self._status is not None and now - self._status[0] < self.status_max_age_s:
                return self._status[1]
            result = self.ask(StatusRequest(), StationStatus)
            self._status = (time.monotonic(), result)
            return result

    def readiness(self) -> Mapping[str, bool]:
        try:
            parts = self.ask(ReadinessRequest(), Readiness, timeout_s=2.0)
        except StationDownError:
            return {"station": False}
        return {"station": True, **parts.model_dump()}

    def trigger(self, part_id: str | None = None, view_index: int = 0,
                trigger_id: int | None = None) -> TriggerAnswer:
        return self.ask(_build(TriggerRequest, part_id=part_id, view=view_index,
                               trigger_id=trigger_id),
                        TriggerAnswer, timeout_s=35.0)

    def verify(self, by: str) -> VerifyAnswer:
        return self.ask(_build(VerifyRequest, by=by), VerifyAnswer, timeout_s=35.0)

    def handeye(self, step: str, by: str, holdout: int | None = None,
                robot_pose: list[float] | None = None) -> HandEyeAnswer:
        # a calculate solves and writes its report (tens of seconds with many poses)
        return self.ask(_build(HandEyeRequest, step=step, by=by, holdout=holdout,
                               robot_pose=robot_pose), HandEyeAnswer, timeout_s=300.0)

    def arm_teach(self, by: str) -> ArmTeachAnswer:
        return self.ask(_build(ArmTeachRequest, by=by), ArmTeachAnswer)

    def teach_from_measurement(self, measurement_id: int, by: str) -> RecipeAnswer:
        return self.ask(_build(TeachRequest, measurement_id=measurement_id, by=by), RecipeAnswer,
                        timeout_s=35.0)

    def activate_recipe(self, name: str, version: int | None, by: str) -> RecipeAnswer:
        return self.ask(_build(ActivateRecipeRequest, name=name, version=version, by=by),
                        RecipeAnswer, timeout_s=35.0)

    def metrics_text(self) -> str:
        """The station process's Prometheus text (its counters and histograms)."""
        return self.ask(MetricsRequest(), MetricsAnswer, timeout_s=2.0).text

    def move_part(self, offset: list[float]) -> MovePartAnswer:
        """Rehearsal on simulated cameras: the part at ``offset`` from the active reference."""
        return self.ask(_build(MovePartRequest, offset=offset), MovePartAnswer, timeout_s=35.0)

    def camera_view(self, width: int = 640) -> CameraViewAnswer:
        """The live camera view's newest frames (grabbed between triggers, at most 2 a s)."""
        return self.ask(_build(CameraViewRequest, width=width), CameraViewAnswer, timeout_s=5.0)

    def reload_recipes(self) -> None:
        with contextlib.suppress(StationDownError):
            self.ask(ReloadRecipesRequest(), ReloadAnswer, timeout_s=35.0)


R = TypeVar("R", bound=Request)


def _build(model: type[R], **args: Any) -> R:
    """A request from the caller's arguments; a bad one is the caller's error, named."""
    try:
        return model(**args)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(x) for x in first["loc"])
        raise InvalidInputError(f"{model.op}: argument {where!r}: {first['msg']}") from None
