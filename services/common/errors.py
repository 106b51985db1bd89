"""HTTP errors, and the map from a service's domain exceptions to them.

Routes raise :class:`ServiceError` subclasses for what is wrong with the request itself (a
query parameter, a header). Domain modules know nothing of HTTP: they raise their own
exceptions, and each service's ``errors.py`` builds one :class:`ErrorMap` saying which status,
code and ``details`` each of them becomes. The app factory renders both as
``{"error": {"code", "message", "details", "request_id"}}``.
"""

from __future__ import annotations

import errno
import sqlite3
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from robocloud.bounded_json import JsonDepthError, JsonError
from robocloud.cid import CIDError
from services.common.slots import ShareBusy, SlotsBusy

UNKNOWN_SIGNER = "address_not_allowed"
"""The code of an authorizer's 403 for a signer it knows nothing of (no registration): the
one refusal that leaves the request's nonce unused (see ``middleware.SignatureLayer``)."""


class ServiceError(Exception):
    """An error with an HTTP status, a snake_case code and details naming what is wrong."""

    status = 500
    code = "internal_error"

    def __init__(
        self,
        message: str,
        *,
        code: str | None = None,
        details: dict[str, Any] | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.message = message
        if code is not None:
            self.code = code
        self.details = details or {}
        self.headers = headers or {}


class BadRequest(ServiceError):
    status = 400
    code = "bad_request"


class Unauthorized(ServiceError):
    status = 401
    code = "unauthorized"


class Forbidden(ServiceError):
    status = 403
    code = "forbidden"


class NotFound(ServiceError):
    status = 404
    code = "not_found"


class MethodNotAllowed(ServiceError):
    status = 405
    code = "method_not_allowed"


class Conflict(ServiceError):
    status = 409
    code = "conflict"


class PayloadTooLarge(ServiceError):
    status = 413
    code = "payload_too_large"


class UnsupportedMediaType(ServiceError):
    status = 415
    code = "unsupported_media_type"


class RangeNotSatisfiable(ServiceError):
    status = 416
    code = "range_not_satisfiable"


class Unprocessable(ServiceError):
    status = 422
    code = "validation_error"


class TooManyRequests(ServiceError):
    status = 429
    code = "rate_limited"

    def __init__(self, message: str, *, retry_after_s: float, **kwargs: Any) -> None:
        seconds = max(1, round(retry_after_s))
        details = {"retry_after": seconds, **kwargs.pop("details", {})}
        super().__init__(message, details=details, headers={"Retry-After": str(seconds)}, **kwargs)


class Unavailable(ServiceError):
    status = 503
    code = "unavailable"


class BadGateway(ServiceError):
    status = 502
    code = "bad_gateway"


class InsufficientStorage(ServiceError):
    """507: the service's own disk is full, which no change to the request can mend."""

    status = 507
    code = "insufficient_storage"


DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})


def disk_full(exc: BaseException) -> BaseException | None:
    """The error saying the disk (or the quota) is full, ``exc`` or one it was raised from:
    an ``OSError`` of ``ENOSPC`` or ``EDQUOT``, or SQLite's ``SQLITE_FULL``; None when there
    is none. Domain modules re-raise such errors as their own; the chain keeps the cause."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, OSError) and current.errno in DISK_FULL_ERRNOS:
            return current
        if isinstance(current, sqlite3.Error) and (
            getattr(current, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL
        ):
            return current
        current = current.__cause__ or current.__context__
    return None


def error_body(
    status_code: str, message: str, details: dict[str, Any], request_id: str
) -> dict[str, Any]:
    """The JSON error model shared by every service."""
    return {
        "error": {
            "code": status_code,
            "message": message,
            "details": details,
            "request_id": request_id,
        }
    }


def no_details(_: Exception) -> dict[str, Any]:
    return {}


@dataclass(frozen=True)
class ErrorRule:
    """How one domain exception type is answered: status, code, and what goes in ``details``."""

    status: int
    code: str
    details: Callable[[Any], dict[str, Any]] = no_details
    headers: Callable[[Any], dict[str, str]] = field(default=lambda _: {})
    message: Callable[[Any], str] = str
    """The error's message; the exception's text unless the client is to be told otherwise."""


class ErrorMap:
    """Domain exception types to :class:`ErrorRule`; the most specific class in the MRO wins."""

    def __init__(self, rules: Mapping[type[Exception], ErrorRule]) -> None:
        self.rules = dict(rules)

    def __or__(self, other: ErrorMap) -> ErrorMap:
        return ErrorMap({**self.rules, **other.rules})

    def to_service_error(self, exc: Exception) -> ServiceError | None:
        """The HTTP error for ``exc``, or None when no rule covers its type."""
        if isinstance(exc, ServiceError):
            return exc
        for cls in type(exc).__mro__:
            rule = self.rules.get(cls)
            if rule is not None:
                error = ServiceError(
                    rule.message(exc),
                    code=rule.code,
                    details=rule.details(exc),
                    headers=rule.headers(exc),
                )
                error.status = rule.status
                return error
        return None


COMMON_ERRORS = ErrorMap(
    {
        CIDError: ErrorRule(400, "invalid_cid", lambda exc: {"field": exc.field, "cid": exc.text}),
        JsonError: ErrorRule(400, "invalid_json"),
        JsonDepthError: ErrorRule(400, "json_too_deep", lambda exc: {"max_depth": exc.max_depth}),
        SlotsBusy: ErrorRule(
            503,
            "busy",
            lambda exc: {"slots": exc.count, "wait_s": exc.wait_s},
            headers=lambda _: {"Retry-After": "1"},
        ),
        ShareBusy: ErrorRule(
            429,
            "rate_limited",
            lambda exc: {"share": exc.share, "slots": exc.count, "wait_s": exc.wait_s},
            headers=lambda _: {"Retry-After": "1"},
        ),
    }
)
"""Errors of the SDK's wire formats, answered alike by every service."""
