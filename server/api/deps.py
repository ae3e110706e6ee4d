"""FastAPI dependencies as Annotated aliases: services from request.state, principal by role."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Annotated

from fastapi import Depends, Request, Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel
from starlette.concurrency import run_in_threadpool

from server.auth import Principal, Role, authenticate, authenticate_recent, authorize
from server.priority import TriggerFirst
from server.state import Services
from server.store import Store

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


async def current_principal(
    request: Request,
    services: ServicesDep,
    _scheme: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> Principal:
    # _scheme only documents the bearer scheme in OpenAPI; the raw header is checked here so a
    # wrong scheme gets its own message. A trigger that started since the request came in goes
    # first (server.priority). A token verified within the last seconds is known without a
    # query (TokenRepository.recent); otherwise the look-up, a database query, runs in the
    # threadpool, off the event loop.
    if (gate := _gate(request)) is not None:
        await gate.wait()
    tokens, header = services.store.tokens, request.headers.get("authorization")
    principal = authenticate_recent(tokens, header)
    if principal is None:
        principal = await run_in_threadpool(authenticate, tokens, header)
    return principal


def _gate(request: Request) -> TriggerFirst | None:
    gate = getattr(getattr(request.app.state, "runtime", None), "gate", None)
    return gate if isinstance(gate, TriggerFirst) else None


def require(role: Role) -> Callable[..., Awaitable[Principal]]:
    async def dependency(
        request: Request, principal: Annotated[Principal, Depends(current_principal)]
    ) -> Principal:
        # Triggers first, again: one that started during the token look-up goes before the
        # endpoint's work (server.priority).
        if (gate := _gate(request)) is not None:
            await gate.wait()
        return authorize(principal, role)

    dependency.__name__ = f"require_{role.value}"
    return dependency


ReadUser = Annotated[Principal, Depends(require(Role.READ))]
OperatorUser = Annotated[Principal, Depends(require(Role.OPERATOR))]
EngineerUser = Annotated[Principal, Depends(require(Role.ENGINEER))]


def _no_pause() -> None:
    return None


async def get_pause(request: Request) -> Callable[[], None]:
    """A checkpoint for an endpoint's own long work in the threadpool: it returns at once, or
    when the trigger that started meanwhile has ended; all its calls in one request wait at
    most the gate's bound together (server.priority)."""
    gate = _gate(request)
    return gate.budget() if gate is not None else _no_pause


PauseDep = Annotated[Callable[[], None], Depends(get_pause)]


def json_response(model: BaseModel) -> Response:
    """``model`` as JSON by pydantic's own serializer. Returned from an endpoint that declares it
    as ``response_model`` (for the schema), it skips FastAPI's second validation and encoding of
    an object the server has just built (MES clients poll these pages)."""
    return Response(model.model_dump_json(), media_type="application/json")
