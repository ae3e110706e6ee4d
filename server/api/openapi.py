"""The OpenAPI document names every status and media type a route answers, problems included.

A route declares the problems only it raises (``responses=problem_responses(409)``); those any
route of a kind answers are added here from what the route depends on, so they cannot drift:

- every route: 400 (malformed Content-Length) and 413 (body over the limit), from
  :class:`~server.api.problems.BodyLimitMiddleware`, which sees every request;
- a route with parameters or a body: 422 (validation), as application/problem+json;
- a route with a path parameter: 404 (the thing it names may not exist);
- a route behind a token: 401 (missing or unknown token) and, with a role, 403;
- a route on the services (store): 503 (the database does not answer).

FastAPI's own 422 (application/json, ``HTTPValidationError``) is replaced: our handler answers
every error as an RFC 7807 problem (server/api/problems.py).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI
from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute, iter_route_contexts
from starlette.routing import BaseRoute

from server.api.deps import current_principal, get_services
from server.api.problems import PROBLEM_JSON

PROBLEM_REF = "#/components/schemas/Problem"

PROBLEM_SCHEMA: dict[str, Any] = {
    "title": "Problem",
    "description": "RFC 7807 problem details; validation problems add 'errors'.",
    "type": "object",
    "required": ["type", "title", "status", "detail"],
    "properties": {
        "type": {"type": "string"},
        "title": {"type": "string"},
        "status": {"type": "integer"},
        "detail": {"type": "string"},
        "instance": {"type": "string"},
        "errors": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "loc": {"type": "array", "items": {"type": "string"}},
                    "msg": {"type": "string"},
                    "type": {"type": "string"},
                },
            },
        },
    },
    "additionalProperties": True,
}


def problem_response(status: int, description: str | None = None) -> dict[str, Any]:
    return {
        "description": description or f"{HTTPStatus(status).phrase} (problem details)",
        "content": {PROBLEM_JSON: {"schema": {"$ref": PROBLEM_REF}}},
    }


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` of a route or router: these statuses answer problem+json."""
    return {status: problem_response(status) for status in statuses}


def _calls(dependant: Dependant) -> Iterable[Callable[..., Any]]:
    if dependant.call is not None:
        yield dependant.call
    for sub in dependant.dependencies:
        yield from _calls(sub)


def implied_statuses(route: Any) -> set[int]:
    """The problem statuses ``route`` can answer by what it depends on (module docstring)."""
    dependant = route.dependant
    calls = set(_calls(dependant))
    names = {getattr(c, "__name__", "") for c in calls}
    statuses = {400, 413}
    if dependant.path_params or dependant.query_params or dependant.header_params \
            or dependant.cookie_params or route.body_field is not None:
        statuses.add(422)
    if dependant.path_params:
        statuses.add(404)
    if current_principal in calls:
        statuses.add(401)
    if any(n.startswith("require_") for n in names):
        statuses.add(403)
    if get_services in calls:
        statuses.add(503)
    return statuses


_BOUNDS = ("maximum", "minimum", "exclusiveMaximum", "exclusiveMinimum")
# FastAPI passes component schemas through a model whose bounds are floats: 2**63 - 1 comes out
# as 9.223372036854776e18, i.e. 2**63, and a client would think 2**63 is accepted. Integer bounds
# that a float cannot carry are the storage limits (BIGINT, unsigned 64 bit); put them back.
_EXACT = {2**63: 2**63 - 1, -(2**63): -(2**63), 2**64: 2**64 - 1}


def exact_integer_bounds(node: Any) -> Any:
    """Integer schemas' bounds as JSON integers again, in place (see ``_EXACT``)."""
    if isinstance(node, dict):
        if node.get("type") == "integer":
            for key in _BOUNDS:
                value = node.get(key)
                if isinstance(value, float) and value.is_integer():
                    node[key] = _EXACT.get(int(value), int(value))
        for child in node.values():
            exact_integer_bounds(child)
    elif isinstance(node, list):
        for child in node:
            exact_integer_bounds(child)
    return node


def declare_problems(schema: dict[str, Any], routes: Iterable[BaseRoute]) -> dict[str, Any]:
    """Add each route's problem statuses to ``schema`` (in place) and the Problem schema."""
    exact_integer_bounds(schema)
    schema.setdefault("components", {}).setdefault("schemas", {})["Problem"] = PROBLEM_SCHEMA
    paths = schema.get("paths", {})
    # Included routers are contexts around the original APIRoute: path, methods and
    # dependencies as the app serves them (fastapi.routing.iter_route_contexts).
    for route in iter_route_contexts(list(routes)):
        if not isinstance(route.original_route, APIRoute) or not route.include_in_schema:
            continue
        for method in route.methods or ():
            operation = paths.get(route.path_format, {}).get(method.lower())
            if operation is None:
                continue
            responses = operation.setdefault("responses", {})
            declared = {int(k) for k in responses if k.isdigit() and int(k) >= 400}
            for status in sorted(declared | implied_statuses(route)):
                old = responses.get(str(status), {})
                keep = old.get("description") if status in declared and status != 422 else None
                responses[str(status)] = problem_response(status, keep)
            operation["responses"] = dict(sorted(responses.items()))
    _drop_unused(schema, ("HTTPValidationError", "ValidationError"))
    return schema


def _drop_unused(schema: dict[str, Any], names: Iterable[str]) -> None:
    import json

    components = schema["components"]["schemas"]
    for name in names:
        if name in components:
            rest = {k: v for k, v in schema.items() if k != "components"}
            others = {k: v for k, v in components.items() if k not in names}
            if f'"#/components/schemas/{name}"' not in json.dumps([rest, others]):
                del components[name]


def install_openapi(app: FastAPI) -> None:
    """Make ``app.openapi()`` declare the problems (once, when the document is first built)."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = declare_problems(build(), app.routes)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
