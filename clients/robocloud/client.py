"""The base HTTP client every typed SDK client builds on.

It signs state-changing requests (the body's SHA-256 is part of the signature, so the exact
bytes are fixed before sending), retries what is safe to retry, and turns the services' JSON
errors into typed exceptions.
"""

from __future__ import annotations

import hashlib
import json as jsonlib
import time
from collections.abc import Iterable, Mapping
from typing import Any

import httpx

from robocloud.errors import MissingIdentityError, error_class_for
from robocloud.identity import Identity
from robocloud.signing import EMPTY_SHA256, audience_from_answer, sign_request

_UNSIGNED_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
USER_AGENT = "robocloud-sdk/0.1"


def raise_for_error(response: httpx.Response) -> None:
    """Raise the typed ``ApiError`` for an error response, with the service's error fields."""
    if response.status_code < 400:
        return
    if response.is_stream_consumed is False:
        response.read()
    code, message, request_id = "http_error", response.reason_phrase, None
    details: dict[str, Any] = {}
    try:
        body = response.json()
    except ValueError:
        body = None
    if isinstance(body, dict) and isinstance(body.get("error"), dict):
        error = body["error"]
        code = str(error.get("code", code))
        message = str(error.get("message", message))
        details = error.get("details") or {}
        request_id = error.get("request_id")
    request_id = request_id or response.headers.get("x-request-id")
    if response.status_code == 429 and "retry_after" not in details:
        retry_after = response.headers.get("retry-after")
        if retry_after is not None:
            details = {**details, "retry_after": retry_after}
    raise error_class_for(response.status_code)(
        response.status_code, code, message, details, request_id
    )


class ServiceClient:
    """A client for one robocloud service.

    Retries connection failures and 503 with exponential backoff. A retried signed request is
    signed again with a fresh nonce, since the service remembers nonces. Streaming bodies
    (iterables) are sent once and never retried: they cannot be replayed.
    """

    def __init__(
        self,
        base_url: str,
        identity: Identity | None = None,
        *,
        timeout: float = 30.0,
        retries: int = 3,
        backoff_s: float = 0.2,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.base_url = base_url.rstrip("/")
        self.identity = identity
        self.retries = retries
        self.backoff_s = backoff_s
        self._http = httpx.Client(
            base_url=self.base_url,
            timeout=timeout,
            transport=transport,
            headers={"User-Agent": USER_AGENT},
        )

    def __enter__(self) -> ServiceClient:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def request(
        self,
        method: str,
        path: str,
        *,
        params: Mapping[str, Any] | None = None,
        json: Any = None,
        content: bytes | Iterable[bytes] | None = None,
        content_sha256: str | None = None,
        headers: Mapping[str, str] | None = None,
        signed: bool | None = None,
        stream: bool = False,
    ) -> httpx.Response:
        """Send one request and return the response; raise ``ApiError`` on an error status.

        With ``stream=True`` the caller must close the response (use it as a context manager).
        """
        method = method.upper()
        must_sign = method not in _UNSIGNED_METHODS if signed is None else signed
        send_headers = dict(headers or {})
        if json is not None:
            content = jsonlib.dumps(json, separators=(",", ":")).encode()
            send_headers.setdefault("Content-Type", "application/json")
        if isinstance(content, bytes):
            content_sha256 = hashlib.sha256(content).hexdigest()
        elif content is None:
            content_sha256 = EMPTY_SHA256
        elif must_sign and content_sha256 is None:
            raise ValueError("a streamed signed body needs its content_sha256 computed beforehand")
        replayable = content is None or isinstance(content, bytes)
        attempts = self.retries + 1 if replayable else 1
        for attempt in range(attempts):
            request = self._http.build_request(
                method, path, params=params, content=content, headers=send_headers
            )
            if must_sign:
                self._sign(request, content_sha256 or EMPTY_SHA256)
            try:
                response = self._http.send(request, stream=True)
            except (httpx.ConnectError, httpx.ConnectTimeout):
                if attempt + 1 == attempts:
                    raise
                self._sleep(attempt)
                continue
            if response.status_code == 503 and attempt + 1 < attempts:
                response.close()
                self._sleep(attempt)
                continue
            if response.status_code >= 400:
                try:
                    raise_for_error(response)
                finally:
                    response.close()
            if not stream:
                response.read()
                response.close()
            return response
        raise AssertionError("unreachable: the last attempt returns or raises")

    def get_json(self, path: str, **kwargs: Any) -> Any:
        return self.request("GET", path, **kwargs).json()

    def post_json(self, path: str, body: Any = None, **kwargs: Any) -> Any:
        response = self.request("POST", path, json=body, **kwargs)
        return response.json() if response.content else None

    _audience: str | None = None

    def audience(self) -> str:
        """The service's audience, ``GET /v1/audience``, fetched once per client.

        Every signature names it (ROBOCLOUD-REQUEST-V2), so a request signed for this service
        is refused by every other service and deployment.
        """
        if self._audience is None:
            answer = self.request("GET", "/v1/audience", signed=False)
            self._audience = str(audience_from_answer(answer.content))
        return self._audience

    def _sign(self, request: httpx.Request, content_sha256: str) -> None:
        if self.identity is None:
            raise MissingIdentityError(f"{request.method} {request.url.path} must be signed")
        raw_path, _, raw_query = request.url.raw_path.partition(b"?")
        request.headers.update(
            sign_request(
                self.identity.account,
                self.audience(),
                request.method,
                raw_path.decode("ascii"),
                raw_query.decode("ascii"),
                content_sha256,
            )
        )

    def _sleep(self, attempt: int) -> None:
        time.sleep(self.backoff_s * (2**attempt))
