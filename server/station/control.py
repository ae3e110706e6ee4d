"""The control channel of the station process: JSON lines over a Unix socket.

The API process (and `mvpose` tools) reach the station through it for what must go through the
station: a commissioning trigger, teaching, recipe selection and activation, live status and
readiness, the station's metrics (for the API's scrape) and moving the simulated part (a
rehearsal on simulated cameras); the live page reads results from the store. One request per
line::

    {"id": 7, "op": "status", "args": {}}
    → {"id": 7, "ok": true, "result": {...}}
    → {"id": 7, "ok": false, "error": {"kind": "not_found", "message": "..."}}

``args`` and ``result`` are an operation's request and answer models
(server.station.messages), which both ends share. A request whose arguments do not fit its
model is answered ``invalid``, naming the argument and what is wrong with it.

The socket lives in the data directory (mode 0600,
so only the station's own user reaches it); a deployment with two containers shares it through
the data volume. This module is the only one that knows the wire format: the client
(server.station.client) frames its requests and reads its answers with :func:`request_line`
and :func:`read_answer`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
from collections.abc import Callable, Mapping
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from server.errors import ConflictError, InvalidInputError, NotFoundError
from server.metrics import exposition
from server.station.messages import (
    REQUESTS,
    ActivateRecipeRequest,
    ArmTeachAnswer,
    ArmTeachRequest,
    CameraViewRequest,
    ErrorBody,
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

if TYPE_CHECKING:  # the API process imports this module for the framing, not the station
    from server.recipes import ActiveRecipe
    from server.station.core import Station

log = logging.getLogger(__name__)

MAX_LINE = 64 * 1024


# ---------------------------------------------------------------------- the framing


def request_line(op: str, args: Mapping[str, Any], rid: int = 1) -> bytes:
    """One request as it goes over the socket."""
    return json.dumps({"id": rid, "op": op, "args": dict(args)}).encode() + b"\n"


class ChannelError(Exception):
    """The station answered an operation with an error (``kind``: see ErrorBody)."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind
        self.message = message


def read_answer(data: bytes) -> Any:
    """The result of one answer line, or ChannelError with the station's reason."""
    try:
        answer = json.loads(data)
        ok = bool(answer.get("ok"))
    except (ValueError, AttributeError):
        raise ChannelError("internal", f"not a control answer: {data[:80]!r}") from None
    if ok:
        return answer.get("result")
    error = answer.get("error") or {}
    raise ChannelError(str(error.get("kind", "internal")), str(error.get("message", "")))


def _line(message: dict[str, Any]) -> bytes:
    return json.dumps(message, separators=(",", ":"), default=str).encode() + b"\n"


def _error(rid: Any, kind: str, message: str) -> dict[str, Any]:
    return {"id": rid, "ok": False, "error": ErrorBody(kind=kind, message=message).model_dump()}


def _invalid_args(op: str, err: ValidationError) -> str:
    first = err.errors()[0]
    where = ".".join(str(x) for x in first["loc"])
    more = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
    return f"{op}: argument {where!r}: {first['msg']}{more}"


# ---------------------------------------------------------------------- the station's side


def station_metrics(st: Station) -> MetricsAnswer:
    """The station process's Prometheus text, for the API's scrape (server/metrics.py)."""
    if st.services is None:
        raise ConflictError("the station is not started")
    return MetricsAnswer(text=exposition(st.services.metrics))


def recipe_answer(rec: ActiveRecipe) -> RecipeAnswer:
    return RecipeAnswer(name=rec.config.name, version=rec.version, number=rec.number,
                        sha256=rec.sha256,
                        T_rf_from_pf0=rec.config.T_rf_from_pf0.model_dump(mode="json"))


class ControlServer:
    """Serves the control channel for one station, on the station's loop."""

    def __init__(self, station: Station, path: Path) -> None:
        self.station = station
        self.path = Path(path)
        self._server: asyncio.AbstractServer | None = None

    async def start(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()  # a socket file left by a killed station
        self._server = await asyncio.start_unix_server(self._serve, path=str(self.path),
                                                       limit=MAX_LINE)
        os.chmod(self.path, 0o600)

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
            self._server = None
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                try:
                    line = await reader.readline()
                except (ValueError, asyncio.LimitOverrunError):
                    await _send(writer, _error(None, "invalid",
                                               f"request longer than {MAX_LINE} bytes"))
                    return
                if not line:
                    return
                try:
                    req = json.loads(line)
                    rid, op, args = req.get("id"), str(req["op"]), req.get("args") or {}
                    if not isinstance(args, dict):
                        raise TypeError("args is not an object")
                except (ValueError, KeyError, TypeError, AttributeError):
                    await _send(writer, _error(None, "invalid", "not a control request"))
                    return
                await _send(writer, await self._handle(rid, op, args))
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()

    async def _handle(self, rid: Any, op: str, args: dict[str, Any]) -> dict[str, Any]:
        model = REQUESTS.get(op)
        if model is None:
            return _error(rid, "invalid", f"unknown control operation {op!r}")
        try:
            request = model.model_validate(args)
        except ValidationError as err:
            return _error(rid, "invalid", _invalid_args(op, err))
        try:
            answer = await self._dispatch(request)
        except ValidationError:  # an answer that does not fit its model: a bug of ours
            log.exception("control operation %s: the answer does not fit its model", op)
            return _error(rid, "internal", f"the station's answer to {op!r} is malformed")
        except KeyError as err:
            return _error(rid, "not_found", str(err.args[0]) if err.args else str(err))
        except NotFoundError as err:
            return _error(rid, "not_found", str(err))
        except (ValueError, InvalidInputError) as err:
            return _error(rid, "invalid", str(err))
        except ConflictError as err:
            return _error(rid, "conflict", str(err))
        except TimeoutError:
            return _error(rid, "busy", "the station did not answer in time")
        except Exception as err:  # noqa: BLE001 — the caller gets a reason, the log the trace
            log.exception("control operation %s failed", op)
            return _error(rid, "internal", f"{type(err).__name__}: {err}")
        return {"id": rid, "ok": True, "result": answer.model_dump(mode="json")}

    async def _dispatch(self, request: Request) -> Message:
        """The operation ``request`` names, on the station; its answer model."""
        if isinstance(request, TriggerRequest):
            return await self._trigger(request)
        if isinstance(request, VerifyRequest):
            # on the station loop, as a link's command runs: the trigger is the station's own
            out, report, _ = await asyncio.wait_for(
                self.station.verify_report("rest", request.by), 30.0)
            return VerifyAnswer(result_code=out.result_code, result_id=out.result_id,
                                message=out.message, report=report)
        if isinstance(request, HandEyeRequest):
            return await self._handeye(request)
        if isinstance(request, CameraViewRequest):
            # on the camera view's own thread (real-time below the trigger path, not the pool)
            return await self.station.camera_view.frames(request.width)
        work = self._work(request)
        return await asyncio.to_thread(work)

    async def _handeye(self, request: HandEyeRequest) -> HandEyeAnswer:
        """A hand-eye step on the station loop, as a link's command runs."""
        he = self.station.handeye
        by = request.by
        if request.step == "begin":
            out = await he.begin("rest", by, request.holdout)
        elif request.step == "pose":
            pose = tuple(request.robot_pose) if request.robot_pose is not None else None
            out = await he.add_pose("rest", by, pose)
        elif request.step == "calculate":
            out = await he.calculate("rest", by)
        else:
            out = he.last
        return HandEyeAnswer(**asdict(out), session=he.status())

    def _work(self, request: Request) -> Callable[[], Message]:
        """The blocking operations, run in a worker thread (never on the station loop)."""
        st = self.station
        match request:
            case PingRequest():
                return lambda: PingAnswer(pid=os.getpid(), station=st.station.name)
            case StatusRequest():
                return lambda: StationStatus.model_validate(st.status())
            case ReadinessRequest():
                return lambda: Readiness.model_validate(st.readiness())
            case ArmTeachRequest(by=by):
                return lambda: ArmTeachAnswer(armed=True, recipe=st.arm_teach(by).config.name)
            case TeachRequest(measurement_id=mid, by=by):
                return lambda: recipe_answer(st.teach_from_measurement(mid, by))
            case ActivateRecipeRequest(name=name, version=version, by=by):
                return lambda: recipe_answer(st.activate_recipe(name, version, by))
            case ReloadRecipesRequest():
                return lambda: ReloadAnswer(changed=st.reload_recipes())
            case MetricsRequest():
                return lambda: station_metrics(st)
            case MovePartRequest(offset=offset):
                # imported here: the API process imports this module for its framing only
                from server.station.rehearsal import move_part

                return lambda: MovePartAnswer.model_validate(move_part(st, offset))
        raise InvalidInputError(f"control operation {request.op!r} has no handler")

    async def _trigger(self, args: TriggerRequest) -> TriggerAnswer:
        from drivers.links import LinkRequest

        req = LinkRequest(link="rest", trigger_id=args.trigger_id or 0,
                          view_index=args.view, robot_pose=None,
                          part_id=args.part_id or "", recipe=0)
        if self.station.active is None:
            raise ConflictError("the station has no recipe selected")
        answer = await asyncio.wait_for(self.station.measure_answer(req), 30.0)
        out = answer.outcome
        db_id = answer.db_id
        if db_id is None and answer.on_committed is not None:
            # A commissioning caller wants the database id (to teach from it, to look it up):
            # wait for the commit a little; a database that is down gives null, the result id
            # stays the key.
            loop = asyncio.get_running_loop()
            committed: asyncio.Future[int] = loop.create_future()

            def settle(db_id: int) -> None:
                if not committed.done():
                    committed.set_result(db_id)

            answer.on_committed(lambda db_id: loop.call_soon_threadsafe(settle, db_id))
            with contextlib.suppress(TimeoutError):
                db_id = await asyncio.wait_for(committed, 2.0)
        return TriggerAnswer(
            result_code=out.result_code, result_id=out.result_id,
            final=out.final, views_done=out.views_done,
            processing_ms=out.processing_ms,
            offset=list(out.offset) if out.offset is not None else None,
            sigma_trans_mm=out.sigma_trans_mm, sigma_rot_deg=out.sigma_rot_deg,
            message=answer.message, measurement_id=db_id, record=answer.record,
            event=answer.event)


async def _send(writer: asyncio.StreamWriter, message: dict[str, Any]) -> None:
    writer.write(_line(message))
    await writer.drain()
