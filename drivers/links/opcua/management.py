"""The VisionSystem's result, recipe and configuration management methods (OPC 40100-1 §7-8).

Each method answers in the standard's structures (the NodeSet's own types, as asyncua builds
them from the imported model) and never raises into the session: what is wrong is the ``Error``
output, a code of the one reason table (``mvpose_core.reasons``), with the text in the link's
``last_errors``. The station answers every query (``StationHandler.get_result`` ...) off its
loop and its trigger thread. No handles are handed out (every handle output is 0): a query's
whole answer is in its outputs, nothing is kept for the client, and ``Timeout`` is not used.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from dataclasses import replace
from typing import Any

from asyncua import Node, Server, ua

from mvpose_core.reasons import Reason

from ..base import CalibrationInfo, ResultQuery, StationHandler
from ..result import ResultEvent
from . import values as v

log = logging.getLogger(__name__)
_UA: Any = ua
MAX_LIST = 100  # the most entries one list answer holds (MaxResults 0 or more: this many)

Outputs = list[ua.Variant]


class Management:
    """Result, recipe and configuration management of one VisionSystem."""

    def __init__(self, handler: StationHandler, on_recipe_change: Callable[[], Awaitable[None]],
                 error: Callable[[str], None], spacing_s: float) -> None:
        self.handler = handler
        self.on_recipe_change = on_recipe_change
        self.error = error
        self.active_configuration: Node | None = None
        # the stored calibrations' versions by sha256, as show_configuration last read them
        # (the result events' InternalConfigurationId.Version)
        self.versions: dict[str, int] = {}
        self.engineer_methods: set[ua.NodeId] = set()
        # one management call at a time, whichever client, spacing_s apart (the station file's
        # query_spacing_s): clients queue instead of adding their load to the trigger path's
        # process, where each call costs tens of ms of Python (decoding records, encoding)
        self.spacing_s = spacing_s
        self._one = asyncio.Lock()
        self._last = -spacing_s

    async def build(self, server: Server, vs: Node, mv: int) -> None:
        """Link the methods of RecipeManagement, ResultManagement and ConfigurationManagement
        (the station's calibration)."""
        rm = await vs.get_child(f"{mv}:RecipeManagement")
        res = await vs.get_child(f"{mv}:ResultManagement")
        cm = await vs.get_child(f"{mv}:ConfigurationManagement")
        self.active_configuration = await cm.get_child(f"{mv}:ActiveConfiguration")
        links: dict[tuple[Node, str], Callable[..., Any]] = {
            (rm, "GetRecipeListFiltered"): self._get_recipe_list,
            (rm, "UnprepareRecipe"): self._unprepare_recipe,
            (res, "GetResultById"): self._get_result_by_id,
            (res, "GetResultComponentsById"): self._get_result_components_by_id,
            (res, "GetResultListFiltered"): self._get_result_list,
            (cm, "GetConfigurationById"): self._get_configuration_by_id,
            (cm, "GetConfigurationList"): self._get_configuration_list,
            (cm, "ActivateConfiguration"): self._activate_configuration,
        }
        for (parent, method), fn in links.items():
            node = await parent.get_child(f"{mv}:{method}")
            server.link_method(node, self._guarded(method, fn))
            if method == "ActivateConfiguration":
                self.engineer_methods.add(node.nodeid)

    def _guarded(self, method: str, fn: Callable[..., Awaitable[tuple[Outputs, int]]]
                 ) -> Callable[..., Awaitable[Outputs]]:
        """``fn`` returns its outputs without Error, and the error code; an exception becomes
        HANDLER_FAILED with the outputs' defaults (the session stays)."""

        async def call(parent: ua.NodeId, *args: ua.Variant) -> Outputs:
            try:
                async with self._one:
                    loop = asyncio.get_running_loop()
                    await asyncio.sleep(self._last + self.spacing_s - loop.time())
                    self._last = loop.time()
                    outputs, code = await fn(*args)
            except Exception as err:
                log.exception("OPC UA %s failed", method)
                self.error(f"{method}: {type(err).__name__}: {err}")
                outputs, code = await self.defaults(method), int(Reason.HANDLER_FAILED)
            return [*outputs, v.int32(code)]

        return call

    async def defaults(self, method: str) -> Outputs:
        """What a method answers besides its Error when it has nothing to say."""
        empty_list = [v.boolean(True), v.uint32(0), v.uint32(v.NO_HANDLE)]
        return {
            "GetRecipeListFiltered": [*empty_list, _structs([])],
            "UnprepareRecipe": [ua.Variant(_UA.RecipeIdInternalDataType(Id=""))],
            "GetResultById": [v.uint32(v.NO_HANDLE), ua.Variant(_UA.ResultDataType())],
            "GetResultComponentsById": _components(None, {}),
            "GetResultListFiltered": [*empty_list, _structs([])],
            "GetConfigurationById": [v.uint32(v.NO_HANDLE),
                                     ua.Variant(_UA.ConfigurationDataType())],
            "GetConfigurationList": [*empty_list, _structs([])],
            "ActivateConfiguration": [],
        }[method]

    # ------------------------------------------------------------------ recipes
    async def _get_recipe_list(self, external: ua.Variant, product: ua.Variant,
                               prepared: ua.Variant, max_results: ua.Variant,
                               start: ua.Variant, *timeout: ua.Variant) -> tuple[Outputs, int]:
        wanted = v.struct_id(external.Value)
        recipes = await self.handler.recipes()
        if wanted:
            recipes = [r for r in recipes if str(r.number) == wanted or r.name == wanted]
        if v.struct_id(product.Value):
            recipes = []  # mvpose has no products
        tri = int(prepared.Value or 0) if prepared.Value is not None else 2
        if tri in (0, 1):
            recipes = [r for r in recipes if r.selected == bool(tri)]
        page, complete = _page(recipes, start.Value, max_results.Value)
        ids = [v.recipe_id("RecipeIdInternalDataType", r.name, r.version, r.sha256, r.number)
               for r in page]
        return [v.boolean(complete), v.uint32(len(ids)), v.uint32(v.NO_HANDLE),
                _structs(ids)], 0

    async def _unprepare_recipe(self, external: ua.Variant, internal: ua.Variant
                                ) -> tuple[Outputs, int]:
        wanted = v.struct_id(external.Value) or v.struct_id(internal.Value)
        recipes = await self.handler.recipes()
        found = next((r for r in recipes if wanted and wanted in (str(r.number), r.name)), None)
        out = [ua.Variant(_UA.RecipeIdInternalDataType(Id=""))]
        if found is None:
            self.error(f"UnprepareRecipe: the station has no recipe {wanted!r}")
            return out, int(Reason.UNKNOWN_RECIPE)
        out = [ua.Variant(v.recipe_id("RecipeIdInternalDataType", found.name, found.version,
                                      found.sha256, found.number))]
        if not found.selected:
            self.error(f"UnprepareRecipe: recipe {found.number} ({found.name}) is not prepared")
            return out, int(Reason.BAD_ARGUMENT)
        code = await self.handler.unselect_recipe()
        await self.on_recipe_change()
        return out, code

    # ------------------------------------------------------------------ results
    async def _one_result(self, method: str, rid: ua.Variant) -> ResultEvent | None:
        wanted = v.struct_id(rid.Value)
        found = None
        if wanted.isdigit() and 0 < int(wanted) < 2**63:
            found = await self.handler.get_result(int(wanted))
        if found is None:
            self.error(f"{method}: no result with ResultId {wanted!r} (ids are record numbers)")
        return found

    async def _config_versions(self) -> dict[str, int]:
        return {c.sha256: c.version for c in await self.handler.calibrations()}

    async def _get_result_by_id(self, rid: ua.Variant, *timeout: ua.Variant
                                ) -> tuple[Outputs, int]:
        found = await self._one_result("GetResultById", rid)
        if found is None:
            return await self.defaults("GetResultById"), int(Reason.BAD_ARGUMENT)
        data = v.result_data(found, await self._config_versions())
        return [v.uint32(v.NO_HANDLE), ua.Variant(data)], 0

    async def _get_result_components_by_id(self, rid: ua.Variant, *timeout: ua.Variant
                                           ) -> tuple[Outputs, int]:
        found = await self._one_result("GetResultComponentsById", rid)
        if found is None:
            return _components(None, {}), int(Reason.BAD_ARGUMENT)
        return _components(found, await self._config_versions()), 0

    async def _get_result_list(self, state: ua.Variant, meas: ua.Variant, part: ua.Variant,
                               external_recipe: ua.Variant, internal_recipe: ua.Variant,
                               external_config: ua.Variant, internal_config: ua.Variant,
                               product: ua.Variant, job: ua.Variant, max_results: ua.Variant,
                               start: ua.Variant, *timeout: ua.Variant) -> tuple[Outputs, int]:
        empty = await self.defaults("GetResultListFiltered")
        query, code = await self._result_query(state, meas, part, external_recipe,
                                               internal_recipe, external_config,
                                               internal_config, job)
        if code:
            return empty, code
        if query is None or v.struct_id(product.Value):  # nothing can match (no products)
            return empty, 0
        limit = _limit(max_results.Value)
        first = int(start.Value or 0)
        found, total = await self.handler.find_results(replace(query, start=first, limit=limit))
        versions = await self._config_versions()
        data = [v.result_data(r, versions) for r in found]
        complete = first + len(found) >= total
        return [v.boolean(complete), v.uint32(len(data)), v.uint32(v.NO_HANDLE),
                _structs(data)], 0

    async def _result_query(self, state: ua.Variant, meas: ua.Variant, part: ua.Variant,
                            external_recipe: ua.Variant, internal_recipe: ua.Variant,
                            external_config: ua.Variant, internal_config: ua.Variant,
                            job: ua.Variant) -> tuple[ResultQuery | None, int]:
        """The filter arguments as a query; (None, 0) when nothing can match; (None, code)
        for an argument mvpose cannot filter by."""
        ok, reason = None, None
        st = int(state.Value or 0)
        if st == v.RESULT_STATE_COMPLETED:
            ok = True
        elif st == v.RESULT_STATE_FAILED:
            ok = False
        elif st < 0:
            ok, reason = False, -st
        elif st != 0:
            return None, 0  # Processing (2), Aborted (3): mvpose stores neither
        triggers = {s for s in (v.struct_id(meas.Value), v.struct_id(job.Value)) if s}
        if len(triggers) > 1 or any(not t.isdigit() for t in triggers):
            return None, 0  # MeasId and JobId are the trigger id: two ids match nothing
        recipe = v.struct_id(internal_recipe.Value) or None
        if number := v.struct_id(external_recipe.Value):
            named = {str(r.number): r.name for r in await self.handler.recipes()}
            if number not in named:
                self.error(f"GetResultListFiltered: the station has no recipe number {number!r}")
                return None, int(Reason.UNKNOWN_RECIPE)
            if recipe is not None and recipe != named[number]:
                return None, 0
            recipe = named[number]
        if v.struct_id(external_config.Value) or v.struct_id(internal_config.Value):
            self.error("GetResultListFiltered: results are not filtered by configuration "
                       "(leave ExternalConfigurationId and InternalConfigurationId empty)")
            return None, int(Reason.BAD_ARGUMENT)
        return ResultQuery(part_id=v.struct_id(part.Value) or None, recipe=recipe,
                           trigger_id=int(next(iter(triggers))) if triggers else None,
                           ok=ok, reason_code=reason), 0

    # ------------------------------------------------------------------ configurations
    async def _find_configuration(self, method: str, cid: ua.Variant
                                  ) -> CalibrationInfo | None:
        """By ``Version`` (the store's version number); a non-empty ``Id`` must be that
        version's calibration id."""
        version, name = v.struct_version(cid.Value), v.struct_id(cid.Value)
        found = None
        if version.isdigit():
            found = next((c for c in await self.handler.calibrations()
                          if c.version == int(version)), None)
        if found is None or (name and name != found.calibration_id):
            self.error(f"{method}: no configuration with Version {version!r} and Id {name!r} "
                       "(Version: the calibration's stored version number)")
            return None
        return found

    async def _get_configuration_by_id(self, cid: ua.Variant, *timeout: ua.Variant
                                       ) -> tuple[Outputs, int]:
        found = await self._find_configuration("GetConfigurationById", cid)
        if found is None:
            return await self.defaults("GetConfigurationById"), int(Reason.BAD_ARGUMENT)
        return [v.uint32(v.NO_HANDLE), ua.Variant(v.configuration(found))], 0

    async def _get_configuration_list(self, max_results: ua.Variant, start: ua.Variant,
                                      *timeout: ua.Variant) -> tuple[Outputs, int]:
        page, complete = _page(await self.handler.calibrations(), start.Value,
                               max_results.Value)
        return [v.boolean(complete), v.uint32(len(page)), v.uint32(v.NO_HANDLE),
                _structs([v.configuration(c) for c in page])], 0

    async def _activate_configuration(self, cid: ua.Variant) -> tuple[Outputs, int]:
        found = await self._find_configuration("ActivateConfiguration", cid)
        if found is None:
            return [], int(Reason.BAD_ARGUMENT)
        code, text = await self.handler.activate_calibration(found.version, "opcua")
        if code:
            self.error(f"ActivateConfiguration: version {found.version}: {text}")
        await self.show_configuration()
        return [], code

    async def show_configuration(self) -> None:
        """ActiveConfiguration: the calibration version the station measures with."""
        if self.active_configuration is None:
            return
        calibrations = await self.handler.calibrations()
        using = next((c for c in calibrations if c.in_use), None)
        self.versions = {c.sha256: c.version for c in calibrations}
        value = v.configuration(using) if using is not None else _UA.ConfigurationDataType()
        await self.active_configuration.write_value(ua.Variant(value))


def _limit(max_results: Any) -> int:
    n = int(max_results or 0)
    return MAX_LIST if n <= 0 else min(n, MAX_LIST)


def _page(items: list[Any], start: Any, max_results: Any) -> tuple[list[Any], bool]:
    first = int(start or 0)
    page = items[first:first + _limit(max_results)]
    return page, first + len(page) >= len(items)


def _structs(items: list[Any]) -> ua.Variant:
    return ua.Variant(items, ua.VariantType.ExtensionObject)


def _components(r: ResultEvent | None, versions: dict[str, int]) -> Outputs:
    """GetResultComponentsById's outputs but Error, from ResultDataType's fields."""
    d = v.result_data(r, versions) if r is not None else _UA.ResultDataType()
    return [
        v.boolean(False), v.uint32(v.NO_HANDLE), v.boolean(d.IsPartial), v.boolean(False),
        v.int32(d.ResultState), ua.Variant(d.MeasId or _UA.MeasIdDataType()),
        ua.Variant(d.PartId or _UA.PartIdDataType()),
        ua.Variant(_UA.RecipeIdExternalDataType(Id="")), ua.Variant(d.InternalRecipeId),
        ua.Variant(_UA.ProductIdDataType(Id="")),
        ua.Variant(_UA.ConfigurationIdDataType(Id="")), ua.Variant(d.InternalConfigurationId),
        ua.Variant(d.JobId), ua.Variant(d.CreationTime, ua.VariantType.DateTime),
        ua.Variant(d.ProcessingTimes or _UA.ProcessingTimesDataType(StartTime=d.CreationTime,
                                                                     EndTime=d.CreationTime)),
        ua.Variant(d.ResultContent or [], ua.VariantType.Variant),
    ]
