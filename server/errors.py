"""Domain errors of the server layer; server/api/problems.py renders each as RFC 7807."""

from __future__ import annotations

from typing import Any, ClassVar


class DomainError(Exception):
    """Base of every error the service reports to a client; ``status`` is the HTTP status."""

    status: ClassVar[int] = 400
    title: ClassVar[str] = "Bad request"
    slug: ClassVar[str] = "bad-request"

    def __init__(self, detail: str, **extra: Any) -> None:
        super().__init__(detail)
        self.detail = detail
        self.extra = extra


class InvalidInputError(DomainError):
    status = 400
    title = "Invalid input"
    slug = "invalid-input"


class UnauthenticatedError(DomainError):
    status = 401
    title = "Authentication required"
    slug = "unauthenticated"


class ForbiddenError(DomainError):
    status = 403
    title = "Forbidden"
    slug = "forbidden"


class NotFoundError(DomainError):
    status = 404
    title = "Not found"
    slug = "not-found"


class ConflictError(DomainError):
    status = 409
    title = "Conflict"
    slug = "conflict"


class PayloadTooLargeError(DomainError):
    status = 413
    title = "Payload too large"
    slug = "payload-too-large"


class StoreUnavailableError(DomainError):
    status = 503
    title = "Store unavailable"
    slug = "store-unavailable"


class NotReadyError(DomainError):
    status = 503
    title = "Not ready"
    slug = "not-ready"


class StationFailedError(DomainError):
    """The station process answered, but with a failure of its own (a bug there, not the
    client's request): the gateway's answer, not a 500 of the API."""

    status = 502
    title = "Station failed"
    slug = "station-failed"


class TooManyAttemptsError(DomainError):
    """A login refused without checking the secret: too many wrong ones in a row just now."""

    status = 429
    title = "Too many attempts"
    slug = "too-many-attempts"
