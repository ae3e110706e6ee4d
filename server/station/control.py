"""The control channel of the station process: JSON lines over a Unix socket.

The API process (and `mvpose` tools) reach the station through it for what must go through the
station: a commissioning trigger, teaching, recipe selection and activation, live status and
readiness, the station's metrics (for the API's scrape), moving the simulated part (a rehearsal
on simulated cameras), and a stream of results for live pages. One request per line::

    {"id": 7, "op": "status", "args": {}}
    → {"id": 7, "ok": true, "result": {...}}
    → {"id": 7, "ok": false, "error": {"kind": "not_found", "message": "..."}}

The socket lives in the data directory (mode 0600,
so only the station's own user reaches it); a deployment with two containers shares it through
the data volume. This module is the only one that knows the wire format.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from server.errors import ConflictError, InvalidInputError, NotFoundError
from server.metrics import exposition
from server.recipes import ActiveRecipe
from server.station.core import Station
from server.station.rehearsal import move_part

log = logging.getLogger(__name__)

MAX_LINE = 64 * 1024


def recipe_info(rec: ActiveRecipe) -> dict[str, Any]:
    return {"name": rec.config.name, "version": rec.version, "number": rec.number,
            "sha256": rec.sha256, "T_rf_from_pf0": rec.config.T_rf_from_pf0.model_dump()}


def station_metrics(st: Station) -> dict[str, str]:
    """The station process's Prometheus text, for the API's scrape (server/metrics.py)."""
    if st.services is None:
        raise ConflictError("the station is not started")
    return {"text": exposition(st.services.metrics)}


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
                    await _send(writer, {"id": None, "ok": False, "error": {
                        "kind": "invalid", "message": f"request longer than {MAX_LINE} bytes"}})
                    return
                if not line:
                    return
                try:
                    req = json.loads(line)
                    rid, op, args = req.get("id"), str(req["op"]), dict(req.get("args") or {})
                except (ValueError, KeyError, TypeError, AttributeError):
                    await _send(writer, {"id": None, "ok": False, "error": {
                        "kind": "invalid", "message": "not a control request"}})
                    return
                await _send(writer, await self._handle(rid, op, args))
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()

    async def _handle(self, rid: Any, op: str, args: dict[str, Any]) -> dict[str, Any]:
        st = self.station
        ops: dict[str, Callable[[], Any]] = {
            "ping": lambda: {"pid": os.getpid(), "station": st.station.name},
            "status": st.status,
            "readiness": st.readiness,
            "arm_teach": lambda: {"armed": True,
                                  "recipe": st.arm_teach(_text(args, "by")).config.name},
            "teach": lambda: recipe_info(st.teach_from_measurement(
                _int(args, "measurement_id"), _text(args, "by"))),
            "activate_recipe": lambda: recipe_info(st.activate_recipe(
                _text(args, "name"), _opt_int(args, "version"), _text(args, "by"))),
            "reload_recipes": lambda: {"changed": st.reload_recipes()},
            "metrics": lambda: station_metrics(st),
            "move_part": lambda: move_part(st, _floats(args, "offset")),
        }
        try:
            if op == "trigger":
                result: Any = await self._trigger(args)
            elif op in ops:
                result = await asyncio.to_thread(ops[op])
            else:
                raise InvalidInputError(f"unknown control operation {op!r}")
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
        return {"id": rid, "ok": True, "result": result}

    async def _trigger(self, args: dict[str, Any]) -> dict[str, Any]:
        from drivers.links import LinkRequest

        req = LinkRequest(link="rest", trigger_id=_opt_int(args, "trigger_id") or 0,
                          view_index=_opt_int(args, "view") or 0, robot_pose=None,
                          part_id=str(args.get("part_id") or ""), recipe=0)
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
        return {
            "result_code": out.result_code, "result_id": out.result_id,
            "final": out.final, "views_done": out.views_done,
            "processing_ms": out.processing_ms,
            "offset": list(out.offset) if out.offset is not None else None,
            "sigma_trans_mm": out.sigma_trans_mm, "sigma_rot_deg": out.sigma_rot_deg,
            "message": answer.message, "measurement_id": db_id,
            "record": answer.record.model_dump(mode="json") if answer.record else None,
            "event": answer.event.to_dict() if answer.event is not None else None,
        }


async def _send(writer: asyncio.StreamWriter, message: dict[str, Any]) -> None:
    writer.write(json.dumps(message, separators=(",", ":"), default=str).encode() + b"\n")
    await writer.drain()


def _error(rid: Any, kind: str, message: str) -> dict[str, Any]:
    return {"id": rid, "ok": False, "error": {"kind": kind, "message": message}}


def _text(args: dict[str, Any], name: str) -> str:
    value = args.get(name)
    if not isinstance(value, str) or not value:
        raise InvalidInputError(f"argument {name!r} must be a non-empty string")
    return value


def _int(args: dict[str, Any], name: str) -> int:
    value = args.get(name)
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidInputError(f"argument {name!r} must be an integer, got {value!r}")
    return value


def _floats(args: dict[str, Any], name: str) -> list[float]:
    value = args.get(name)
    if not isinstance(value, list) or not all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in value):
        raise InvalidInputError(f"argument {name!r} must be a list of numbers, got {value!r}")
    return [float(v) for v in value]


def _opt_int(args: dict[str, Any], name: str) -> int | None:
    return None if args.get(name) is None else _int(args, name)
