"""Exceptions raised by the SDK, one hierarchy so callers can catch precisely.

``ApiError`` carries the service's JSON error (code, message, details, request id) so that a
robot can log the request id and a human can find the matching server log line.
"""

from __future__ import annotations

from typing import Any


class RobocloudError(Exception):
    """Base of every error the SDK raises."""


class FormatError(RobocloudError, ValueError):
    """Bytes or text that do not follow a wire format (CID, CAR, dag-pb, UnixFS, JSON, ...).

    Each format module raises its own subclass, whose message names what is wrong and where.
    """


class SignatureError(RobocloudError):
    """A signed request is malformed or its signature does not verify.

    ``code`` is the snake_case error code a service returns; ``header`` names the offending
    header when there is one.
    """

    def __init__(self, code: str, message: str, header: str | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.header = header


class KeystoreError(RobocloudError):
    """A keystore file is missing, unreadable, or the passphrase is wrong."""


class MissingIdentityError(RobocloudError):
    """A request must be signed but the client was built without an identity."""


class ApiError(RobocloudError):
    """A service answered with an error status and (usually) the JSON error model."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        details: dict[str, Any] | None = None,
        request_id: str | None = None,
    ) -> None:
        super().__init__(f"{status} {code}: {message}")
        self.status = status
        self.code = code
        self.message = message
        self.details = details or {}
        self.request_id = request_id


class BadRequestError(ApiError):
    """400: the request was malformed."""


class AuthenticationError(ApiError):
    """401: missing or invalid signature, stale timestamp or reused nonce."""


class PermissionDeniedError(ApiError):
    """403: the signer is not allowed to do this."""


class NotFoundError(ApiError):
    """404: no such resource."""


class ConflictError(ApiError):
    """409: the resource is not in a state that allows the request."""


class PayloadTooLargeError(ApiError):
    """413: the body exceeds the service's limit."""


class UnsupportedMediaTypeError(ApiError):
    """415: the body's content type is not accepted by the route."""


class RangeNotSatisfiableError(ApiError):
    """416: the requested byte range lies outside the content."""


class ValidationError(ApiError):
    """422: the body parsed but a field is invalid; ``details`` names the field paths."""


class RateLimitedError(ApiError):
    """429: too many requests; ``retry_after`` says when to come back, in seconds."""

    @property
    def retry_after(self) -> float | None:
        value = self.details.get("retry_after")
        return float(value) if value is not None else None


class ServerError(ApiError):
    """5xx: the service failed."""


class UnavailableError(ServerError):
    """503: the service is not ready; the client retries these with backoff."""


_BY_STATUS: dict[int, type[ApiError]] = {
    400: BadRequestError,
    401: AuthenticationError,
    403: PermissionDeniedError,
    404: NotFoundError,
    409: ConflictError,
    413: PayloadTooLargeError,
    415: UnsupportedMediaTypeError,
    416: RangeNotSatisfiableError,
    422: ValidationError,
    429: RateLimitedError,
    503: UnavailableError,
}


def error_class_for(status: int) -> type[ApiError]:
    """The most specific ``ApiError`` subclass for an HTTP status."""
    if status in _BY_STATUS:
        return _BY_STATUS[status]
    return ServerError if status >= 500 else ApiError
