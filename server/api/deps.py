"""FastAPI dependencies as Annotated aliases: services from request.state, principal by role."""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from server.auth import Principal, Role, authenticate, authorize
from server.state import Services
from server.store import Store

_bearer = HTTPBearer(auto_error=False, description="API token: Authorization: Bearer mvp_…")


def get_services(request: Request) -> Services:
    services: Services = request.state.services
    return services


ServicesDep = Annotated[Services, Depends(get_services)]


def get_store(services: ServicesDep) -> Store:
    return services.store


StoreDep = Annotated[Store, Depends(get_store)]


def current_principal(
    request: Request,
    services: ServicesDep,
    _scheme: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> Principal:
    # _scheme only documents the bearer scheme in OpenAPI; the raw header is checked here so a
    # wrong scheme gets its own message. A plain def: the look-up is a database query, so
    # FastAPI runs it in the threadpool, off the event loop.
    return authenticate(services.store.tokens, request.headers.get("authorization"))


def require(role: Role) -> Callable[[Principal], Principal]:
    def dependency(principal: Annotated[Principal, Depends(current_principal)]) -> Principal:
        return authorize(principal, role)

    dependency.__name__ = f"require_{role.value}"
    return dependency


ReadUser = Annotated[Principal, Depends(require(Role.READ))]
OperatorUser = Annotated[Principal, Depends(require(Role.OPERATOR))]
EngineerUser = Annotated[Principal, Depends(require(Role.ENGINEER))]
