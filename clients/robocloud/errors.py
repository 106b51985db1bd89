"""Exceptions raised by the SDK, one hierarchy so callers can catch precisely.

Everything derives from :class:`RobocloudError`, split by who is at fault, because that decides
what a robot does next::

    RobocloudError
    ├── FormatError          bytes or text that break a wire format (CID, CAR, JSON, ...)
    ├── SignatureError       a request signature is malformed or does not verify
    ├── KeystoreError        the robot's own key cannot be read
    ├── MissingIdentityError a write was attempted without a key
    ├── ConfigurationError   a service URL or setting cannot be used
    ├── TransportError       no answer: connection refused, timeout, broken connection
    │   ├── ConnectError         the request never left: always safe to retry
    │   └── TransportTimeoutError
    ├── ApiError             the service answered an error status (its JSON error, request id)
    │   └── BadRequestError, AuthenticationError, ..., ServerError, UnavailableError
    ├── InvalidAnswerError   the service answered, but the answer is malformed or fails
    │                        verification (``robocloud.cas.CasError`` is one)
    └── LedgerError          ``robocloud.ledger``: RpcError (JSON-RPC error objects),
                             RevertError, TransactionTimeoutError, ...

``ApiError`` carries the service's JSON error (code, message, details, request id) so that a
robot can log the request id and a human can find the matching server log line. Transport
errors keep httpx's exception as ``__cause__``; no httpx exception leaves the SDK.

This module imports nothing beyond the standard library, so ``import robocloud.errors`` stays
cheap for callers that only catch.
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


class ConfigurationError(RobocloudError, ValueError):
    """A setting or argument cannot be used, such as a service URL that is not http(s)."""


class TransportError(RobocloudError):
    """No usable answer: the service could not be reached, or the connection broke or timed out.

    ``service`` names the service (``cas``, ``ledger``, ...) when the client knows it, so a
    caller can say which ``ROBOCLOUD_<SERVICE>_URL`` to check; ``url`` is the request's URL.
    httpx's exception is the ``__cause__``.
    """

    def __init__(self, message: str, *, method: str, url: str, service: str | None) -> None:
        super().__init__(message)
        self.method = method
        self.url = url
        self.service = service


class ConnectError(TransportError):
    """The connection could not be opened (refused, unknown host, connect timeout).

    Nothing was sent, so any request, a write included, may be retried.
    """


class TransportTimeoutError(TransportError):
    """The service accepted the connection but did not answer (or finish answering) in time.

    A write may or may not have taken effect.
    """


class InvalidAnswerError(RobocloudError):
    """A service answered, but what it said cannot be used: malformed, oversized, or it fails
    verification (a CID that does not match, a JSON document nested past the bound).

    The service is broken or lying; retrying the same service is unlikely to help.
    """


MAX_SHOWN_CHARS = 1024
"""Characters of a peer's error message or revert reason an exception's text holds: a peer
may send megabytes, which a service keeps (the storage node's last anchoring error), logs and
serves. The whole text stays on the exception's own attribute (``message``, ``reason``)."""


def shown_text(text: str) -> str:
    """``text`` whole, or its first ``MAX_SHOWN_CHARS`` and how long it was."""
    if len(text) <= MAX_SHOWN_CHARS:
        return text
    return f"{text[:MAX_SHOWN_CHARS]}... ({len(text)} characters)"


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
        super().__init__(f"{status} {shown_text(code)}: {shown_text(message)}")
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
        return retry_after_seconds(self.details.get("retry_after"))


def retry_after_seconds(value: object) -> float | None:
    """A ``Retry-After`` (header text, or the number in a 429's details) in seconds; None when
    there is none or it is no number: an HTTP date is valid there (RFC 9110), and the
    details are whatever the service wrote."""
    if isinstance(value, bool) or not isinstance(value, str | int | float):
        return None
    try:
        return float(value)
    except ValueError:
        return None


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
