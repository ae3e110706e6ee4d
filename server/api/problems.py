"""RFC 7807 problem responses: the one place that maps errors to HTTP, and the body-size limit."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.routing import iter_route_contexts
from pydantic import ValidationError
from sqlalchemy.exc import OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from mvpose_core.station import StationFileError
from server.errors import DomainError, InvalidInputError, PayloadTooLargeError

log = logging.getLogger(__name__)

PROBLEM_TYPE = "https://mvpose.invalid/problems/"
PROBLEM_JSON = "application/problem+json"


def problem(
    status: int, title: str, detail: str, slug: str, instance: str | None = None,
    headers: Mapping[str, str] | None = None, **extra: Any,
) -> JSONResponse:
    body = {"type": PROBLEM_TYPE + slug, "title": title, "status": status, "detail": detail}
    if instance:
        body["instance"] = instance
    body.update(extra)
    out = dict(headers or {})
    if status == 401:
        out["WWW-Authenticate"] = "Bearer"
    return JSONResponse(body, status_code=status, media_type=PROBLEM_JSON, headers=out or None)


def _errors(errors: list[Any]) -> list[dict[str, Any]]:
    # Only loc, msg and type: 'input' may be bytes or huge, and 'ctx' may hold exceptions.
    return [
        {
            "loc": [str(p) for p in e.get("loc", ())],
            "msg": str(e.get("msg", "")),
            "type": str(e.get("type", "")),
        }
        for e in errors
    ]


def allowed_methods(app: Any, path: str) -> str:
    """The ``Allow`` value of ``path``: the methods of every route on it (Starlette's own 405
    names only the first route that matched the path, e.g. GET but not the POST beside it)."""
    methods: set[str] = set()
    for route in iter_route_contexts(list(app.routes)):
        regex, route_methods = getattr(route, "path_regex", None), route.methods
        if regex is not None and route_methods and regex.match(path):
            methods |= route_methods
    return ", ".join(sorted(methods))


def _to_response(exc: Exception, path: str) -> JSONResponse:
    if isinstance(exc, DomainError):
        return problem(exc.status, exc.title, exc.detail, exc.slug, path, **exc.extra)
    if isinstance(exc, RequestValidationError | ValidationError):
        errs = _errors(list(exc.errors()))
        detail = "; ".join(f"{'.'.join(e['loc'])}: {e['msg']}" for e in errs[:5])
        return problem(422, "Validation failed", detail, "validation", path, errors=errs)
    if isinstance(exc, StationFileError):
        return problem(422, "Invalid station content", str(exc), "station", path)
    if isinstance(exc, OperationalError):
        # The database is unreachable, locked past its busy timeout, or out of disk: not the
        # client's fault and not a bug here; retrying later can succeed.
        log.error("database unavailable on %s: %s", path, exc.orig)
        return problem(503, "Store unavailable", f"the database did not answer: "
                       f"{type(exc.orig).__name__}", "store-unavailable", path)
    if isinstance(exc, StarletteHTTPException):
        # Its headers matter: a 405 carries Allow (the methods the path answers).
        return problem(
            exc.status_code,
            _REASON.get(exc.status_code, "HTTP error"),
            str(exc.detail),
            f"http-{exc.status_code}",
            path,
            headers=exc.headers,
        )
    log.exception("unhandled error on %s", path, exc_info=exc)
    return problem(
        500, "Internal error", "an unexpected error; see the server log", "internal", path
    )


_REASON = {
    404: "Not found",
    405: "Method not allowed",
    400: "Bad request",
    401: "Unauthorized",
    403: "Forbidden",
    406: "Not acceptable",
    415: "Unsupported media type",
}


def install_problem_handlers(app: FastAPI) -> None:
    """Every error becomes application/problem+json through :func:`_to_response`, and the
    app's OpenAPI document says so for every route (server/api/openapi.py)."""
    from server.api.openapi import install_openapi  # it imports this module

    install_openapi(app)

    async def handler(request: Request, exc: Exception) -> JSONResponse:
        if isinstance(exc, StarletteHTTPException) and exc.status_code == 405:
            allow = allowed_methods(request.app, request.url.path)
            exc = StarletteHTTPException(405, exc.detail, {**(exc.headers or {}), "Allow": allow})
        return _to_response(exc, request.url.path)

    for exc_type in (
        DomainError,
        RequestValidationError,
        ValidationError,
        StationFileError,
        StarletteHTTPException,
        OperationalError,
        Exception,
    ):
        app.add_exception_handler(exc_type, handler)


class _BodyTooLargeError(Exception):
    pass


class BodyLimitMiddleware:
    """Refuse request bodies over ``max_bytes`` with 413, by Content-Length or while streaming."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None:
            try:
                too_big = int(declared) > self.max_bytes
            except ValueError:
                await self._refuse(
                    send, scope, InvalidInputError(f"Content-Length {declared!r} is not a number")
                )
                return
            if too_big:
                await self._refuse(send, scope, self._error(int(declared)))
                return
        seen = 0
        refused = False
        started = False

        async def limited_receive() -> Message:
            nonlocal seen, refused
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.max_bytes:
                    refused = True
                    raise _BodyTooLargeError
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if refused:
                return  # the app's answer to a truncated body is replaced by our 413
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, limited_receive, guarded_send)
        except _BodyTooLargeError:
            refused = True
        if refused and not started:
            await self._refuse(send, scope, self._error(seen))

    def _error(self, size: int) -> PayloadTooLargeError:
        return PayloadTooLargeError(
            f"request body of {size} bytes or more exceeds the limit of {self.max_bytes} bytes",
            limit_bytes=self.max_bytes,
        )

    async def _refuse(self, send: Send, scope: Scope, err: DomainError) -> None:
        response = _to_response(err, scope.get("path", ""))
        await send(
            {
                "type": "http.response.start",
                "status": response.status_code,
                "headers": response.raw_headers,
            }
        )
        await send({"type": "http.response.body", "body": response.body})
