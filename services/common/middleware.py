"""The request guard: request ids, metrics, access logs, body limits and signatures.

It is plain ASGI so that it can act before any body byte is read: a request without a valid
signature gets 401 at once, one announcing too large a body 413 at once. While the body
streams in, its size is counted and its SHA-256 computed; a body that grows past the limit
or does not match the signed digest makes ``receive()`` raise, so a route that streams into
storage must stage what it writes and commit only once the body completed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import time
import uuid
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from robocloud.errors import SignatureError
from robocloud.signing import verify_request
from services.common.auth import Authorizer
from services.common.errors import (
    BadRequest,
    PayloadTooLarge,
    ServiceError,
    Unauthorized,
    error_body,
)
from services.common.logs import request_id_var
from services.common.metrics import ServiceMetrics
from services.common.nonces import NonceStore

log = logging.getLogger("robocloud.http")

UNSIGNED_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
INTERNAL_ERROR = ServiceError("internal error; see the service log")
_REQUEST_ID = re.compile(r"[A-Za-z0-9._-]{8,64}")


@dataclass
class GuardConfig:
    """What the guard enforces for one service."""

    max_body_bytes: int
    max_clock_skew_s: int
    authorizer: Authorizer
    nonces: NonceStore
    metrics: ServiceMetrics
    unsigned_paths: frozenset[str] = frozenset()
    body_limits: Mapping[str, int] = field(default_factory=dict)

    def body_limit(self, path: str) -> int:
        """The limit of the longest configured path prefix, else the service default."""
        matches = [p for p in self.body_limits if path.startswith(p)]
        return self.body_limits[max(matches, key=len)] if matches else self.max_body_bytes


async def send_error(send: Send, error: ServiceError, request_id: str) -> None:
    body = json.dumps(error_body(error.code, error.message, error.details, request_id)).encode()
    headers = [
        (b"content-type", b"application/json"),
        (b"content-length", str(len(body)).encode()),
        *((k.lower().encode(), v.encode()) for k, v in error.headers.items()),
    ]
    await send({"type": "http.response.start", "status": error.status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


class BodyMeter:
    """Wraps ``receive`` to enforce the size limit and the signed digest while streaming."""

    def __init__(self, receive: Receive, limit: int, expected_sha256: str | None) -> None:
        self._receive = receive
        self._limit = limit
        self._expected = expected_sha256
        self._hash = hashlib.sha256() if expected_sha256 is not None else None
        self.received = 0

    async def __call__(self) -> Message:
        message = await self._receive()
        if message["type"] != "http.request":
            return message
        chunk: bytes = message.get("body", b"")
        self.received += len(chunk)
        if self.received > self._limit:
            raise PayloadTooLarge(
                f"the body exceeds the limit of {self._limit} bytes",
                details={"limit": self._limit},
            )
        if self._hash is not None:
            self._hash.update(chunk)
            if not message.get("more_body", False) and self._hash.hexdigest() != self._expected:
                raise BadRequest(
                    "the body does not match X-Robocloud-Content-SHA256; nothing was stored",
                    code="body_digest_mismatch",
                    details={"header": "X-Robocloud-Content-SHA256", "expected": self._expected},
                )
        return message


class RequestGuard:
    def __init__(self, app: ASGIApp, config: GuardConfig) -> None:
        self.app = app
        self.config = config

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        offered = headers.get("x-request-id", "")
        request_id = offered if _REQUEST_ID.fullmatch(offered) else uuid.uuid4().hex
        token = request_id_var.set(request_id)
        started = time.perf_counter()
        status = {"code": 0}

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
                message["headers"] = [
                    *message.get("headers", []),
                    (b"x-request-id", request_id.encode()),
                ]
            await send(message)

        try:
            await self._guarded(scope, receive, send_with_id, headers, request_id)
        except Exception as exc:
            # Answered here rather than by Starlette's outermost handler so that the log line
            # and the answer carry the request id; a response already started is cut off.
            log.exception("unhandled error", exc_info=exc)
            if status["code"]:
                raise
            await send_error(send_with_id, INTERNAL_ERROR, request_id)
        finally:
            self._record(scope, status["code"] or 500, time.perf_counter() - started)
            request_id_var.reset(token)

    async def _guarded(
        self, scope: Scope, receive: Receive, send: Send, headers: Headers, request_id: str
    ) -> None:
        path: str = scope["path"]
        limit = self.config.body_limit(path)
        declared = headers.get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            error = PayloadTooLarge(
                f"Content-Length {declared} exceeds the limit of {limit} bytes",
                details={"header": "Content-Length", "limit": limit},
            )
            await send_error(send, error, request_id)
            return
        expected_sha256 = None
        if scope["method"] not in UNSIGNED_METHODS and path not in self.config.unsigned_paths:
            try:
                expected_sha256 = await self._authenticate(scope, headers)
            except ServiceError as error:
                await send_error(send, error, request_id)
                return
        started = False

        async def tracking_send(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, BodyMeter(receive, limit, expected_sha256), tracking_send)
        except ServiceError as error:
            # A body error raised under a handler that does not map it (e.g. while a
            # streaming route was consuming the body); answer it here if still possible.
            if started:
                raise
            await send_error(send, error, request_id)

    async def _authenticate(self, scope: Scope, headers: Headers) -> str:
        raw_path = scope.get("raw_path") or scope["path"].encode()
        raw_path = raw_path.split(b"?", 1)[0]
        try:
            verified = verify_request(
                scope["method"],
                raw_path.decode("latin-1"),
                scope.get("query_string", b"").decode("latin-1"),
                headers,
                max_skew_s=self.config.max_clock_skew_s,
            )
        except SignatureError as exc:
            raise Unauthorized(
                exc.message, code=exc.code, details={"header": exc.header} if exc.header else {}
            ) from exc
        await self.config.authorizer.authorize(verified.address)
        if not self.config.nonces.use(verified.address, verified.nonce, verified.timestamp):
            raise Unauthorized(
                "this nonce was already used by this address",
                code="replayed_nonce",
                details={"header": "X-Robocloud-Nonce"},
            )
        scope.setdefault("state", {})["signature"] = verified
        return verified.content_sha256

    def _record(self, scope: Scope, status: int, seconds: float) -> None:
        route = scope.get("route")
        template = getattr(route, "path", None) or "unmatched"
        self.config.metrics.observe(scope["method"], template, status, seconds)
        signature = scope.get("state", {}).get("signature")
        extra: dict[str, Any] = {
            "method": scope["method"],
            "path": scope["path"],
            "route": template,
            "status": status,
            "duration_ms": round(seconds * 1000, 2),
        }
        if signature is not None:
            extra["signer"] = signature.address
        log.info("request", extra=extra)
