"""Service errors as plain exceptions, mapped to the JSON error model in one place.

Domain modules raise these (they import nothing from the web framework); the app factory turns
each into ``{"error": {"code", "message", "details", "request_id"}}`` with its status.
"""

from __future__ import annotations

from typing import Any


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
