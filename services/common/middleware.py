"""The request guard: five plain ASGI layers, each with one job, outermost first.

1. :class:`RequestIdLayer` gives every request an id (the log lines and the answer carry it)
   and answers whatever escapes the layers below with a 500 in the error model (507 when the
   service's disk is full).
2. :class:`AccessLogLayer` records metrics by route template and writes one access-log line.
3. :class:`BodyLimitLayer` refuses a body over the path's limit: 413 at once when
   ``Content-Length`` says so, else as soon as the streamed body grows past it.
4. :class:`SignatureLayer` checks the signature of a write before any body byte is read (401
   at once), then the body's SHA-256 while it streams in.
5. :class:`DiskReserveLayer` keeps the disk's last bytes from uploads (507 when a write would
   take them), for the service's own small writes and the deletions that free space.

They are plain ASGI rather than Starlette's ``BaseHTTPMiddleware`` so that they act before the
body is read. The body checks raise from the ``receive`` they hand down: a route that streams
into storage must stage what it writes and commit only once the body completed. Each layer
answers the errors it raises itself; when a route lets one escape before it started its
answer, the layer that raised it answers it.
"""

from __future__ import annotations

import abc
import hashlib
import json
import logging
import math
import re
import time
import uuid
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import anyio

# Loaded at start: robocloud.signing imports eth-account on first use (a second's import, which
# robots' read-only commands skip), and a service's first signed request must not wait on it.
import eth_account  # noqa: F401
from starlette.datastructures import Headers
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from robocloud.errors import SignatureError
from robocloud.signing import HEADER_CONTENT_SHA256, WrongAudienceError, verify_request
from services.common.audience import ServiceAudience
from services.common.auth import Authorizer
from services.common.disk import DiskReserve, ReserveReached
from services.common.errors import (
    UNKNOWN_SIGNER,
    BadRequest,
    Forbidden,
    InsufficientStorage,
    PayloadTooLarge,
    ServiceError,
    TooManyRequests,
    Unauthorized,
    Unavailable,
    disk_full,
    error_body,
)
from services.common.logs import request_id_var
from services.common.metrics import ServiceMetrics
from services.common.nonces import (
    NonceQuotaExceeded,
    NonceStore,
    NonceStoreFull,
    StrangerNonces,
)
from services.common.slots import client_key, client_var

log = logging.getLogger("robocloud.http")

UNSIGNED_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
CLIENT_CLOSED_REQUEST = 499
INTERNAL_ERROR = ServiceError("internal error; see the service log")
DISK_FULL = InsufficientStorage(
    "the service's disk is full, so this request failed; it may succeed once the service's "
    "operator has freed space"
)
REQUEST_ID_SCOPE_KEY = "robocloud.request_id"
"""Where the request id is also kept in the ASGI scope, for the server protocol's log lines."""
SERVER_ANSWER_SCOPE_KEY = "robocloud.server_answer"
"""The status the server protocol answered itself while the app still ran (a 408 for a body
that stopped coming): what the access log records instead of the app's disconnection."""
_REQUEST_ID = re.compile(r"[A-Za-z0-9._-]{8,64}")


async def send_error(send: Send, error: ServiceError) -> None:
    """Answer ``error`` in the JSON error model, with the current request id."""
    body = error_body(error.code, error.message, error.details, request_id_var.get())
    encoded = json.dumps(body).encode()
    headers = [
        (b"content-type", b"application/json"),
        (b"content-length", str(len(encoded)).encode()),
        *((k.lower().encode(), v.encode()) for k, v in error.headers.items()),
    ]
    await send({"type": "http.response.start", "status": error.status, "headers": headers})
    await send({"type": "http.response.body", "body": encoded})


class _ResponseWatch:
    """Wraps ``send`` to know whether the answer started, and with which status."""

    def __init__(self, send: Send) -> None:
        self._send = send
        self.status = 0

    async def __call__(self, message: Message) -> None:
        if message["type"] == "http.response.start":
            self.status = message["status"]
        await self._send(message)


class _BodyMeter(abc.ABC):
    """Wraps ``receive``; ``check`` sees each chunk and the end, and may raise a ServiceError.

    The error raised is kept so that the layer that installed the meter can tell its own
    errors from others' when one escapes the app.
    """

    def __init__(self, receive: Receive) -> None:
        self._receive = receive
        self.error: ServiceError | None = None

    async def __call__(self) -> Message:
        message = await self._receive()
        if message["type"] == "http.request":
            try:
                self.check(message.get("body", b""), not message.get("more_body", False))
            except ServiceError as error:
                self.error = error
                raise
        return message

    @abc.abstractmethod
    def check(self, chunk: bytes, last: bool) -> None:
        """Raise a ServiceError when the body so far breaks the rule the meter enforces."""


async def _run_metered(app: ASGIApp, scope: Scope, meter: _BodyMeter, send: Send) -> None:
    """Run ``app`` reading through ``meter``; answer the meter's own error if it escapes."""
    watch = _ResponseWatch(send)
    try:
        await app(scope, meter, watch)
    except ServiceError as error:
        if error is not meter.error or watch.status:
            raise
        await send_error(watch, error)


class RequestIdLayer:
    """Every request gets an id: a client's ``X-Request-Id`` of 8 to 64 safe characters, else
    a new one. It is in the ``request_id`` context variable (so every log line written while
    serving carries it), in the answer's ``X-Request-Id``, and in a 500 for an exception that
    nothing below handled, logged with the same id. Who asks (``slots.client_key`` of the peer
    address) goes in the ``client`` context variable, which the shares of costly turns count.

    A full disk is a 507 (``insufficient_storage``) instead, logged in one line: the robot
    learns that the failure is the service's and lasts until its operator frees space, and the
    operator reads that once a request, not a traceback.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        offered = Headers(scope=scope).get("x-request-id", "")
        request_id = offered if _REQUEST_ID.fullmatch(offered) else uuid.uuid4().hex
        token = request_id_var.set(request_id)
        peer = scope.get("client")
        client_token = client_var.set(None if peer is None else client_key(peer[0]))
        scope[REQUEST_ID_SCOPE_KEY] = request_id

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                message["headers"] = [
                    *message.get("headers", []),
                    (b"x-request-id", request_id.encode()),
                ]
            await send(message)

        watch = _ResponseWatch(send_with_id)
        try:
            await self.app(scope, receive, watch)
        except ClientDisconnect:
            # Nobody is left to answer; what the route staged was discarded on the way out,
            # and the access log's line (status 499) is the one record of it.
            pass
        except Exception as exc:
            if watch.status:
                log.exception("unhandled error", exc_info=exc)
                raise
            full = disk_full(exc)
            if full is not None:
                log.error("the disk is full: %s", full)
                await send_error(watch, DISK_FULL)
            else:
                log.exception("unhandled error", exc_info=exc)
                await send_error(watch, INTERNAL_ERROR)
        finally:
            client_var.reset(client_token)
            request_id_var.reset(token)


class AccessLogLayer:
    """Metrics by route template (bounded label cardinality) and one log line per request.

    The line carries method, path, route, status, duration, the client's address and, for a
    signed request, the signer. An exception passing through counts as 500, which is what the
    client gets; a client that went away mid-request counts as 499, nginx's "client closed
    request".
    """

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        watch = _ResponseWatch(send)
        status = 0
        try:
            await self.app(scope, receive, watch)
        except ClientDisconnect:
            status = scope.get(SERVER_ANSWER_SCOPE_KEY, CLIENT_CLOSED_REQUEST)
            raise
        finally:
            self._record(scope, watch.status or status or 500, time.perf_counter() - started)

    def _record(self, scope: Scope, status: int, seconds: float) -> None:
        route = scope.get("route")
        template = getattr(route, "path", None) or "unmatched"
        self.metrics.observe(scope["method"], template, status, seconds)
        extra: dict[str, Any] = {
            "method": scope["method"],
            "path": scope["path"],
            "route": template,
            "status": status,
            "duration_ms": round(seconds * 1000, 2),
            "client": client_var.get(),
        }
        signature = scope.get("state", {}).get("signature")
        if signature is not None:
            extra["signer"] = signature.address
        log.info("request", extra=extra)


class _SizeMeter(_BodyMeter):
    def __init__(self, receive: Receive, limit: int) -> None:
        super().__init__(receive)
        self.limit = limit
        self.received = 0

    def check(self, chunk: bytes, last: bool) -> None:
        self.received += len(chunk)
        if self.received > self.limit:
            raise PayloadTooLarge(
                f"the body exceeds the limit of {self.limit} bytes",
                details={"limit": self.limit},
            )


class BodyLimitLayer:
    """At most ``default_limit`` body bytes, or the limit of the longest matching prefix in
    ``limits`` (uploads). Checked against ``Content-Length`` before anything is read, and
    counted while the body streams, so a chunked body cannot exceed it either.
    """

    def __init__(
        self, app: ASGIApp, default_limit: int, limits: Mapping[str, int] | None = None
    ) -> None:
        self.app = app
        self.default_limit = default_limit
        self.limits = dict(limits or {})

    def limit_for(self, path: str) -> int:
        """The limit of the longest configured path prefix, else the default."""
        matches = [prefix for prefix in self.limits if path.startswith(prefix)]
        return self.limits[max(matches, key=len)] if matches else self.default_limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.limit_for(scope["path"])
        declared = Headers(scope=scope).get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            error = PayloadTooLarge(
                f"Content-Length {declared} exceeds the limit of {limit} bytes",
                details={"header": "Content-Length", "limit": limit},
            )
            await send_error(send, error)
            return
        await _run_metered(self.app, scope, _SizeMeter(receive, limit), send)


class _DigestMeter(_BodyMeter):
    def __init__(self, receive: Receive, expected_sha256: str) -> None:
        super().__init__(receive)
        self.expected = expected_sha256
        self.hash = hashlib.sha256()

    def check(self, chunk: bytes, last: bool) -> None:
        self.hash.update(chunk)
        if last and self.hash.hexdigest() != self.expected:
            raise BadRequest(
                f"the body does not match {HEADER_CONTENT_SHA256}; nothing was stored",
                code="body_digest_mismatch",
                details={"header": HEADER_CONTENT_SHA256, "expected": self.expected},
            )


class SignatureLayer:
    """Writes (every method but GET, HEAD and OPTIONS) must be signed for this service.

    Before the body is read, in order: the audience must be known (503), the signature
    headers valid for this audience (401, see ``robocloud.signing``), the signer authorized
    (403, or 503 when the ledger cannot say), and the nonce unused (401 ``replayed_nonce``).
    While the body streams its SHA-256 is checked against the signed one (400). Paths in
    ``unsigned_paths`` carry their own authentication (the chain's JSON-RPC). A request no
    route takes (``routed`` says which do) goes on unsigned to its 404 or 405, which writes
    nothing: an IPFS client calling a kubo method cas does not offer (``ipfs id``) was told
    "header X-Robocloud-Address is required", as if signing would have made it work.

    The nonce is recorded after the authorizer answered, so that a stranger (a self-made key
    the registry has no record of, 403 ``address_not_allowed``) leaves nothing behind: free
    keys would otherwise fill the nonce store, and a full store refuses every robot's writes.
    Replays stay refused: the check and the record are one step under the store's lock,
    taken after the authorizer's await, so of two copies racing one gets through; a replay
    costs an authorizer lookup, cached. Every other answer records the nonce, refusals
    included, so that they are final: a 503 (the ledger down), after which the SDK retries
    with a fresh nonce, and a 403 for a known robot (pending, inactive) cannot be replayed
    into success once the ledger answers or the robot is approved. A stranger's refused
    request is final too, while its nonce is held in memory (:class:`StrangerNonces`): a copy
    sent once its key is registered and approved is 401 ``replayed_nonce``.
    """

    def __init__(
        self,
        app: ASGIApp,
        *,
        audience: ServiceAudience,
        nonces: NonceStore,
        authorizer: Authorizer,
        max_clock_skew_s: int,
        unsigned_paths: Iterable[str] = (),
        routed: Callable[[Scope], bool] = lambda _: True,
    ) -> None:
        self.app = app
        self.routed = routed
        self.audience = audience
        self.nonces = nonces
        self.authorizer = authorizer
        self.max_clock_skew_s = max_clock_skew_s
        self.unsigned_paths = frozenset(unsigned_paths)
        self.strangers = StrangerNonces(max_clock_skew_s)
        self._journal = anyio.CapacityLimiter(1)
        """One worker thread records nonces (the store's lock serialises them anyway), so a
        burst of signed writes waits on the event loop, not in threads others need."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] != "http"
            or scope["method"] in UNSIGNED_METHODS
            or scope["path"] in self.unsigned_paths
            or not self.routed(scope)
        ):
            await self.app(scope, receive, send)
            return
        try:
            expected_sha256 = await self._authenticate(scope)
        except ServiceError as error:
            await send_error(send, error)
            return
        await _run_metered(self.app, scope, _DigestMeter(receive, expected_sha256), send)

    async def _authenticate(self, scope: Scope) -> str:
        audience = str(self.audience.require())
        raw_path = scope.get("raw_path") or scope["path"].encode()
        raw_path = raw_path.split(b"?", 1)[0]
        try:
            verified = verify_request(
                scope["method"],
                raw_path.decode("latin-1"),
                scope.get("query_string", b"").decode("latin-1"),
                Headers(scope=scope),
                audience=audience,
                max_skew_s=self.max_clock_skew_s,
            )
        except SignatureError as exc:
            details: dict[str, Any] = {"header": exc.header} if exc.header else {}
            if isinstance(exc, WrongAudienceError):
                details |= {"expected": exc.expected, "received": exc.received}
            raise Unauthorized(exc.message, code=exc.code, details=details) from exc
        scope.setdefault("state", {})["signature"] = verified
        try:
            await self.authorizer.authorize(verified.address)
        except Exception as refused:
            if isinstance(refused, Forbidden) and refused.code == UNKNOWN_SIGNER:
                self.strangers.remember(verified.address, verified.nonce, verified.timestamp)
            else:
                await self._use_nonce(verified.address, verified.nonce, verified.timestamp)
            raise
        await self._use_nonce(verified.address, verified.nonce, verified.timestamp)
        if self.strangers.refused(verified.address, verified.nonce):
            raise _replayed()
        return verified.content_sha256

    async def _use_nonce(self, address: str, nonce: str, timestamp: int) -> None:
        """Record the request's nonce: 401 if it was used, 429 if its signer holds its share
        of the store, 503 if the store is full (a full store refuses new nonces rather than
        forget live ones, which would allow replays).

        The store fsyncs its journal before it returns, and the request goes on only then, so
        a nonce acknowledged survives kill -9; it does so on a worker thread, since an fsync
        per signed write on the event loop held every other request behind the disk.
        """
        try:
            fresh = await anyio.to_thread.run_sync(
                self.nonces.use, address, nonce, timestamp, limiter=self._journal
            )
        except NonceQuotaExceeded as quota:
            raise TooManyRequests(
                f"this address holds its limit of {quota.limit} signed requests within the "
                "clock window; retry later",
                code="nonce_quota_exceeded",
                retry_after_s=math.ceil(quota.retry_after_s),
                details={"limit": quota.limit},
            ) from quota
        except NonceStoreFull as full:
            seconds = max(1, math.ceil(full.retry_after_s))
            raise Unavailable(
                "the service holds as many recent nonces as it can; retry later",
                code="nonce_store_full",
                details={"limit": full.limit, "retry_after": seconds},
                headers={"Retry-After": str(seconds)},
            ) from full
        if not fresh:
            raise _replayed()


def _replayed() -> Unauthorized:
    return Unauthorized(
        "this nonce was already used by this address",
        code="replayed_nonce",
        details={"header": "X-Robocloud-Nonce"},
    )


RESERVE_RECHECK_BYTES = 1 << 20
"""How much of a streamed body arrives between two looks at the disk: a ``statvfs`` costs a
few microseconds, so an upload pays nothing measurable, and the reserve is overrun by at most
about this much (and the batches the route holds) an upload at a time."""


class _ReserveMeter(_BodyMeter):
    def __init__(self, receive: Receive, reserve: DiskReserveLayer) -> None:
        super().__init__(receive)
        self.reserve = reserve
        self.unchecked = 0

    def check(self, chunk: bytes, last: bool) -> None:
        self.unchecked += len(chunk)
        if self.unchecked >= RESERVE_RECHECK_BYTES:
            self.unchecked = 0
            self.reserve.require_room(0)


class DiskReserveLayer:
    """Writes under ``storing_paths`` (uploads, records, ingests) leave the disk's reserve
    (:mod:`services.common.disk`) free: 507 ``insufficient_storage`` when the free space less
    the declared ``Content-Length`` falls under it, before the body is read, and as soon as it
    does while the body streams in.

    It sits inside the signature check, so a refused write has used its nonce (it cannot be
    replayed into success once space is freed) and a stranger learns nothing of the disk.
    """

    def __init__(self, app: ASGIApp, *, reserve: DiskReserve, storing_paths: Iterable[str]) -> None:
        self.app = app
        self.reserve = reserve
        self.storing_paths = tuple(storing_paths)

    def require_room(self, incoming: int) -> None:
        """Raise 507 unless ``incoming`` more bytes leave the reserve free."""
        try:
            self.reserve.require_room(incoming)
        except ReserveReached as reached:
            log.warning(
                "write refused: the disk is down to its reserve",
                extra={
                    "free_bytes": reached.free_bytes,
                    "reserve_bytes": reached.reserve_bytes,
                    "incoming": incoming,
                },
            )
            details: dict[str, Any] = {
                "free_bytes": reached.free_bytes,
                "reserve_bytes": reached.reserve_bytes,
            }
            if incoming:
                details |= {"header": "Content-Length", "declared_bytes": incoming}
            write = f"this write of {incoming} bytes" if incoming else "this write"
            raise InsufficientStorage(
                f"{reached}: {write} is refused and nothing of it kept; it may succeed once data "
                "is deleted or the service's operator frees space",
                details=details,
            ) from None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] != "http"
            or not self.reserve.reserve_bytes
            or scope["method"] in UNSIGNED_METHODS
            or not scope["path"].startswith(self.storing_paths)
        ):
            await self.app(scope, receive, send)
            return
        declared = Headers(scope=scope).get("content-length", "")
        try:
            self.require_room(int(declared) if declared.isdigit() else 0)
        except InsufficientStorage as error:
            await send_error(send, error)
            return
        await _run_metered(self.app, scope, _ReserveMeter(receive, self), send)
