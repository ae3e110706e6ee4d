"""A small StationHandler of the OPC UA tests' own: it records each answer with the next seq and
tells its listeners, as the station does; and the link configuration those tests share."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from drivers.links.base import (
    CalibrationInfo,
    LinkOutcome,
    LinkRequest,
    RecipeInfo,
    ResultQuery,
)
from drivers.links.opcua.settings import OpcUaLinkConfig, hash_password
from drivers.links.result import ResultEvent
from mvpose_core.reasons import Reason
from mvpose_core.transforms import RobotConvention

PASSWORDS = {"olga": "operator-pw", "rita": "reader-pw", "erik": "engineer-pw"}
AT = datetime(2026, 11, 23, 23, 0, tzinfo=UTC)


class RecordingHandler:
    """A station that records every answer with the next seq and tells its listeners (from a
    thread of its own, as the station's recorder thread does)."""

    def __init__(self) -> None:
        self.seq = 100
        self.records: list[tuple[LinkRequest, LinkOutcome]] = []
        self.stored: dict[int, ResultEvent] = {}
        self.calibs = [CalibrationInfo(1, "cal-a", "aa" * 32, AT, "eve", "first", False, False),
                       CalibrationInfo(2, "cal-b", "bb" * 32, AT, "eve", "second", True, True)]
        self.queries = 0
        self.listeners: list[Callable[[ResultEvent], None]] = []
        self.recipe = 1
        self.gate: asyncio.Event | None = None
        self.permits: asyncio.Queue[None] | None = None  # one per measurement, when set
        self.started = asyncio.Event()
        self.resets = 0
        self.entered = 0  # measurements begun
        self.fail = False  # measure raises

    def measure(self, request: LinkRequest) -> asyncio.Future[LinkOutcome]:
        return asyncio.ensure_future(self._measure(request))

    async def _measure(self, request: LinkRequest) -> LinkOutcome:
        self.started.set()
        self.entered += 1
        if self.gate is not None:
            await self.gate.wait()
        if self.permits is not None:
            await self.permits.get()
        if self.fail:
            raise RuntimeError("the station is stopping")
        t = request.trigger_id
        out = LinkOutcome(0, 0, offset=(t * 0.5, -1.0, 2.0, 0.1, 0.2, -0.3),
                          sigma_trans_mm=0.05, sigma_rot_deg=0.01, processing_ms=12.0)
        return self.record(request, out, "OK")

    def record(self, request: LinkRequest, out: LinkOutcome, result: str) -> LinkOutcome:
        self.seq += 1
        out = LinkOutcome(out.result_code, self.seq, out.offset, out.sigma_trans_mm,
                          out.sigma_rot_deg, out.processing_ms)
        self.records.append((request, out))
        code = out.result_code
        event = ResultEvent(
            result_id=self.seq, trigger_id=request.trigger_id, part_id=request.part_id,
            result=result, reason_code=code, reason=Reason(code).name, message="",
            triggered_at=AT, recipe=f"recipe-{self.recipe}", recipe_version=1,
            convention="fanuc" if out.offset else None, offset=out.offset,
            sigma_mm=out.sigma_trans_mm, sigma_deg=out.sigma_rot_deg, processing_ms=12.0,
            calibration_id="cal-b", calibration_sha256="bb" * 32)
        self.stored[self.seq] = event
        for listen in self.listeners:
            th = threading.Thread(target=listen, args=(event,))
            th.start()
            th.join()
        return out

    async def record_failure(self, request: LinkRequest, code: int, message: str,
                             processing_ms: float) -> int:
        return self.record(request, LinkOutcome(code, 0), "NOK").result_id

    async def select_recipe(self, number: int) -> int:
        if number not in (1, 2):
            return int(Reason.UNKNOWN_RECIPE)
        self.recipe = number
        return 0

    async def teach_reference(self, by: str) -> int:
        return 0

    async def reset(self) -> None:
        self.resets += 1

    def convention(self) -> RobotConvention:
        return RobotConvention.FANUC

    def selected_recipe(self) -> int:
        return self.recipe

    def add_listener(self, listen: Callable[[ResultEvent], None]) -> None:
        self.listeners.append(listen)

    async def unselect_recipe(self) -> int:
        self.recipe = 0
        return 0

    async def recipes(self) -> list[RecipeInfo]:
        return [RecipeInfo(n, f"recipe-{n}", n + 2, f"{n:02d}" * 32, n == self.recipe)
                for n in (1, 2)]

    async def get_result(self, result_id: int) -> ResultEvent | None:
        self.queries += 1
        return self.stored.get(result_id)

    async def find_results(self, query: ResultQuery) -> tuple[list[ResultEvent], int]:
        self.queries += 1
        q = query
        found = [r for r in self.stored.values()
                 if (q.part_id is None or r.part_id == q.part_id)
                 and (q.recipe is None or r.recipe == q.recipe)
                 and (q.trigger_id is None or r.trigger_id == q.trigger_id)
                 and (q.ok is None or r.ok == q.ok)
                 and (q.reason_code is None or r.reason_code == q.reason_code)]
        return found[q.start:q.start + q.limit], len(found)

    async def calibrations(self) -> list[CalibrationInfo]:
        return list(self.calibs)

    async def activate_calibration(self, version: int, by: str) -> tuple[int, str]:
        if version == 1 and by == "opcua":
            self.calibs = [replace(c, active=c.version == 1, in_use=c.version == 1)
                           for c in self.calibs]
            return 0, ""
        return int(Reason.BAD_ARGUMENT), f"version {version} does not fit"



def link_config(pki: Path, **extra: Any) -> OpcUaLinkConfig:
    """An OPC UA link on any free port with an operator, a reader and an engineer."""
    users = {"olga": {"role": "operator", "password_hash": hash_password("operator-pw", 10_000)},
             "rita": {"role": "read", "password_hash": hash_password("reader-pw", 10_000)},
             "erik": {"role": "engineer",
                      "password_hash": hash_password("engineer-pw", 10_000)}}
    return OpcUaLinkConfig.model_validate({"port": 0, "pki_dir": str(pki), "users": users,
                                           "measure_timeout_s": 5.0, **extra})
