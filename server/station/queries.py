"""What a link may ask the station besides triggers: stored results, recipes, calibration versions.

The query half of :class:`drivers.links.base.StationHandler`, to which
:class:`server.station.core.Station` delegates. Reads of the store run in a worker thread
(``asyncio.to_thread``) on a pooled connection of their own, never on the station's loop or its
trigger thread, and decode only the page asked for (record summaries, no detections): the trigger
path shares the process's GIL with them. Changes (deselecting the recipe) run on the trigger
thread between triggers; activating a calibration goes the way a REST activation goes (the
store's active version, then the station's reload on the trigger thread).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable

from drivers.links.base import CalibrationInfo, RecipeInfo, ResultQuery
from drivers.links.result import ResultEvent
from mvpose_core.reasons import Reason
from server.errors import InvalidInputError, NotFoundError
from server.station.measuring import Measuring
from server.store import Store
from server.store.events import summary_event
from server.store.schemas import MeasurementFilter
from server.version_checks import check_calibration

MAX_PAGE = 1000  # the most records one query returns (a bigger ask gets this many)
DECODE_CHUNK = 5  # records decoded between two offers of the GIL to the trigger thread


class StationQueries:
    """The StationHandler's queries over ``store``, for the station measuring with
    ``measuring``. Changes go through the callables the station gives: ``between`` runs a
    function on the trigger thread between triggers, ``changed`` tells the links the selected
    recipe changed, ``reload`` makes the station measure with the store's active versions."""

    def __init__(self, store: Store, measuring: Measuring,
                 between: Callable[[Callable[[], None]], Awaitable[None]],
                 changed: Callable[[], None], reload: Callable[[], bool]) -> None:
        self.store = store
        self.measuring = measuring
        self._between = between
        self._changed = changed
        self._reload = reload

    # ------------------------------------------------------------------ results
    async def get_result(self, result_id: int) -> ResultEvent | None:
        return await asyncio.to_thread(self._get_result, result_id)

    async def find_results(self, query: ResultQuery) -> tuple[list[ResultEvent], int]:
        return await asyncio.to_thread(self._find_results, query)

    def _get_result(self, result_id: int) -> ResultEvent | None:
        repo = self.store.measurements
        rows, _ = repo.summary_page(MeasurementFilter(result_id=result_id), None, 1)
        return summary_event(rows[0]) if rows else None

    def _find_results(self, q: ResultQuery) -> tuple[list[ResultEvent], int]:
        result = None if q.ok is None else ("OK" if q.ok else "NOK")
        total, summaries = self.store.measurements.summaries_from(
            MeasurementFilter(result=result, reason_code=q.reason_code, recipe=q.recipe,
                              part_id=q.part_id, trigger_id=q.trigger_id),
            q.start, min(max(q.limit, 0), MAX_PAGE))
        out = []
        for i, summary in enumerate(summaries):
            if i and i % DECODE_CHUNK == 0:
                time.sleep(0)  # hand the GIL to the trigger thread if it waits for it
            out.append(summary_event(summary))
        return out, total

    # ------------------------------------------------------------------ recipes
    async def recipes(self) -> list[RecipeInfo]:
        book = self.measuring.book
        if book is None:
            return []
        selected = book.selected
        return sorted((RecipeInfo(r.number, r.config.name, r.version, r.sha256,
                                  selected is not None and selected.number == r.number)
                       for r in book.recipes.values()), key=lambda r: r.number)

    async def unselect_recipe(self) -> int:
        await self._between(self.measuring.unselect)
        self._changed()
        return 0

    # ------------------------------------------------------------------ calibration
    async def calibrations(self) -> list[CalibrationInfo]:
        return await asyncio.to_thread(self._calibrations)

    async def activate_calibration(self, version: int, by: str) -> tuple[int, str]:
        return await asyncio.to_thread(self._activate_calibration, version, by)

    def _calibrations(self) -> list[CalibrationInfo]:
        versions = self.store.versions
        name = self.measuring.file_station.name
        try:
            infos = versions.versions("calibration", name)
        except NotFoundError:
            return []
        out = []
        for info in infos:
            _, content = versions.content("calibration", name, info.version)
            out.append(CalibrationInfo(
                version=info.version, calibration_id=str(content.get("id", "")),
                sha256=str(content.get("sha256", "")), created_at=info.created_at,
                created_by=info.created_by, comment=info.comment, active=info.active,
                in_use=info.version == self.measuring.calibration_version))
        return out

    def _activate_calibration(self, version: int, by: str) -> tuple[int, str]:
        versions = self.store.versions
        station = self.measuring.file_station
        name = station.name
        try:
            _, content = versions.content("calibration", name, version)
            # the REST upload's own check (content hash, fits the station)
            check_calibration(name, content, station)
        except (NotFoundError, InvalidInputError) as err:
            return int(Reason.BAD_ARGUMENT), str(err)
        versions.activate("calibration", name, version, by)
        self._reload()  # on the trigger thread, between triggers
        return 0, ""
