"""FastAPI dependencies as Annotated aliases: services from request.state, principal by role."""

from __future__ import annotations

import re
from collections.abc import Awaitable, Callable
from datetime import datetime
from typing import TYPE_CHECKING, Annotated, Any

from fastapi import Depends, Request, Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, BeforeValidator, Field
from starlette.concurrency import run_in_threadpool

from server.auth import Principal, Role, authenticate, authenticate_recent, authorize
from server.errors import NotReadyError
from server.state import Services
from server.store import Store
from server.store.schemas import MAX_ID
from server.web.session import cookie_principal

if TYPE_CHECKING:  # server.app imports this module
    from server.app import StationHandle

_bearer = HTTPBearer(auto_error=False, description="API token: Authorization: Bearer mvp_…")


# Dependencies that only pick objects are ``async def``: FastAPI runs a plain ``def`` dependency
# in the threadpool, a thread hop each (~0.1-0.3 ms of CPU under the GIL) for no work.


async def get_services(request: Request) -> Services:
    services: Services = request.state.services
    return services


ServicesDep = Annotated[Services, Depends(get_services)]


async def get_store(services: ServicesDep) -> Store:
    return services.store


StoreDep = Annotated[Store, Depends(get_store)]


def station_of(app: Any) -> StationHandle | None:
    """The app's station handle (``app.state.station``: server.app.create_app's ``station``),
    None when the API runs without a station process."""
    station: StationHandle | None = getattr(app.state, "station", None)
    return station


def need_station(app: Any) -> StationHandle:
    """The app's station handle; NotReadyError (503) when the API runs without one."""
    station = station_of(app)
    if station is None:
        raise NotReadyError("this API runs without a station process")
    return station


async def current_principal(
    request: Request,
    services: ServicesDep,
    _scheme: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> Principal:
    # _scheme only documents the bearer scheme in OpenAPI; the raw header is checked here so a
    # wrong scheme gets its own message. A token verified within the last seconds is known
    # without a query (TokenRepository.recent); otherwise the look-up, a database query, runs in
    # the threadpool, off the event loop.
    tokens, header = services.store.tokens, request.headers.get("authorization")
    if header is None:  # the operator page's session cookie (CSRF-checked there)
        from_cookie = await cookie_principal(request, services)
        if from_cookie is not None:
            return from_cookie
    principal = authenticate_recent(tokens, header)
    if principal is None:
        principal = await run_in_threadpool(authenticate, tokens, header)
    return principal


def require(role: Role) -> Callable[..., Awaitable[Principal]]:
    async def dependency(
        request: Request, principal: Annotated[Principal, Depends(current_principal)]
    ) -> Principal:
        return authorize(principal, role)

    dependency.__name__ = f"require_{role.value}"
    return dependency


ReadUser = Annotated[Principal, Depends(require(Role.READ))]
OperatorUser = Annotated[Principal, Depends(require(Role.OPERATOR))]
EngineerUser = Annotated[Principal, Depends(require(Role.ENGINEER))]


def _json_integer(value: object) -> object:
    # JSON Schema's "integer" (what OpenAPI tells clients) is a number without a fractional
    # part, 5.0 included; true/false and "5" are not numbers (pydantic's lax int takes them).
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError("expected an integer (a JSON number, not a string or true/false)")
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


# Integers of request bodies, bounded (a number beyond the database's BIGINT is the client's
# 422, not an overflow in the driver) and as JSON Schema reads "integer". Field must come
# before the validator, or the bounds drop out of the OpenAPI document.
IdInt = Annotated[int, Field(ge=1, le=MAX_ID), BeforeValidator(_json_integer)]
VersionInt = Annotated[int, Field(ge=1, le=2**31 - 1), BeforeValidator(_json_integer)]
ViewInt = Annotated[int, Field(ge=0, le=255), BeforeValidator(_json_integer)]
Uint32 = Annotated[int, Field(ge=0, le=2**32 - 1), BeforeValidator(_json_integer)]

_ISO_DATE = re.compile(r"\d{4}-\d{2}-\d{2}")


def _iso_only(value: object) -> object:
    # pydantic reads a bare number as Unix time ("0.5" = 1970-01-01T00:00:00.5Z), which would
    # pass a typo silently and skip the time-zone check: only ISO 8601 text is a date here.
    if isinstance(value, str) and not _ISO_DATE.match(value):
        raise ValueError("expected an ISO 8601 date and time with zone, e.g. 2026-11-02T06:00:00Z")
    return value


#: a query parameter's date and time: ISO 8601 text only (format date-time in OpenAPI)
IsoDateTime = Annotated[datetime, BeforeValidator(_iso_only)]


def json_response(model: BaseModel) -> Response:
    """``model`` as JSON by pydantic's own serializer. Returned from an endpoint that declares it
    as ``response_model`` (for the schema), it skips FastAPI's second validation and encoding of
    an object the server has just built (MES clients poll these pages)."""
    return Response(model.model_dump_json(), media_type="application/json")
