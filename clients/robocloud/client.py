"""The base HTTP client every typed SDK client builds on.

One class owns the httpx client, its lifetime (``with``/``close``), request signing, retries,
bounded reading of answers and the translation of failures into the SDK's errors, so that no
httpx exception and no unbounded or over-deep answer reaches a caller. The typed clients are
thin subclasses, one module per service, each naming its service (which also picks its
default URL, ``ROBOCLOUD_<SERVICE>_URL``):

- :class:`robocloud.cas.Cas` (``cas``): kubo RPC and the trustless gateway.
- :class:`robocloud.ledger.LedgerService` (``ledger``): the ledger's REST reads and faucet.
- :class:`robocloud.ledger.JsonRpcClient`: Ethereum JSON-RPC, the ledger's ``/rpc`` or any node.
- ``robocloud.storage.Storage``, ``robocloud.broker.Broker`` and ``robocloud.fl.Fl`` go in the
  same shape: ``class Storage(ServiceClient): default_service = "storage"`` and one typed
  method per route, answers parsed with :meth:`ServiceClient.json_of`.

Clients that span several services (``robocloud.ledger.Ledger``: JSON-RPC plus REST) hold
typed clients and derive from :class:`Closeable` for the same ``with`` behaviour.
"""

from __future__ import annotations

import abc
import hashlib
import json as jsonlib
import time
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Self, TypedDict

import httpx
from typing_extensions import Unpack

from robocloud import bounded_json
from robocloud.config import expected_deployment, service_url
from robocloud.deadline import (
    AnswerClock,
    LowSpeed,
    LowSpeedGuard,
    reads_bounded_by,
    transport_for,
)
from robocloud.errors import (
    ApiError,
    ConfigurationError,
    ConnectError,
    FormatError,
    InvalidAnswerError,
    MissingIdentityError,
    TransportError,
    TransportTimeoutError,
    error_class_for,
    retry_after_seconds,
)
from robocloud.identity import Identity
from robocloud.signing import EMPTY_SHA256, audience_from_answer, sign_request

USER_AGENT = "robocloud-sdk/0.1"
IDEMPOTENT_METHODS = frozenset({"GET", "HEAD", "OPTIONS", "PUT", "DELETE"})
"""RFC 9110's idempotent methods: safe to resend after a broken connection."""
_UNSIGNED_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
MAX_ANSWER_BYTES = 64 << 20
"""The most a non-streamed answer may hold; a larger one is refused as it arrives."""
MAX_WAIT_S = 25.0
"""The longest a long poll may ask a service to wait (``wait_s``: the ledger's new
advertisements, an ingest job's next change): under this client's default read timeout
(30 s), and under what proxies commonly allow an answer to take."""
MAX_ERROR_BYTES = 1 << 20
"""The most of an error answer read from a streamed response (its JSON error is small)."""
ANSWER_DEADLINE_FACTOR = 4
"""An answer read whole must be complete within this many ``timeout``s of the request's last
byte: the timeout bounds each read, so a service dripping a byte per read would otherwise
hold a client as long as it likes."""
BODY_SLICE_BYTES = 1 << 20
"""A bytes body is handed to httpx in slices of this size: given whole, httpcore sends it by
``send`` and ``buffer = buffer[n:]``, copying what is left after each send, so a 256 MiB body
took 6.6 s of copying to send over loopback (quadratic in its size)."""
FILE_BODY_CHUNK = 1 << 20


class FileBody:
    """A file sent as a streamed body, read anew for each attempt: unlike an iterator, a
    request sending it may be resent (``BaseClient.send``), for a route that takes the same
    body twice as once (a bag's ingest). Sent with its ``Content-Length``, never chunked."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.size = path.stat().st_size

    def __iter__(self) -> Iterator[bytes]:
        with self.path.open("rb") as stream:
            while chunk := stream.read(FILE_BODY_CHUNK):
                yield chunk

    def sha256(self) -> str:
        digest = hashlib.sha256()
        for chunk in self:
            digest.update(chunk)
        return digest.hexdigest()


class AnswerDeadlineError(TransportTimeoutError):
    """An answer read whole did not complete within the client's ``answer_deadline_s``.

    Not retried: a service that sends its answer this slowly would do so again.
    """


class RedirectError(InvalidAnswerError):
    """A service answered a redirect (3xx). The SDK follows none (a signed request names its
    audience and path, and a write redirected was not carried out), so an answer that is
    neither a success nor an error is refused rather than taken for a success.
    ``location`` is the service's ``Location`` header (untrusted), if it sent one."""

    def __init__(self, message: str, status: int, location: str | None) -> None:
        super().__init__(message)
        self.status = status
        self.location = location


@dataclass(frozen=True)
class RetryPolicy:
    """How often and how patiently a request is tried again.

    What is retried (see :meth:`BaseClient.send`): a failed connection (nothing was sent),
    503 (the service refused before doing anything) and a 429 whose ``Retry-After`` is within
    ``max_delay_s`` (this client's own requests hold its share of a service's turns; a faucet
    that says come back in an hour is not waited for) for every request whose body can be sent
    again; a broken or timed-out exchange, 502 and 504 only for idempotent requests; an answer
    past its deadline (``AnswerDeadlineError``) never. Delays grow exponentially from
    ``backoff_s``; a ``Retry-After`` is honoured up to ``max_delay_s``.
    """

    retries: int = 3
    backoff_s: float = 0.2
    max_delay_s: float = 5.0

    def delay(self, attempt: int, retry_after: str | None = None) -> float:
        wait: float = self.backoff_s * float(2**attempt)
        asked = retry_after_seconds(retry_after)
        if asked is not None:
            wait = max(wait, asked)
        return min(max(wait, 0.0), self.max_delay_s)


class Closeable(abc.ABC):
    """``with client: ...`` closes the client; every SDK client has this one behaviour."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release connections; the client cannot be used afterwards."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _checked_url(url: str, service: str | None) -> str:
    try:
        parsed = httpx.URL(url)
    except httpx.InvalidURL as exc:
        raise ConfigurationError(f"{url!r} is not a usable URL: {exc}") from exc
    if parsed.scheme not in ("http", "https") or not parsed.host:
        where = f" for {service}" if service else ""
        raise ConfigurationError(f"{url!r}{where} is not an http:// or https:// URL")
    return url.rstrip("/")


class RequestOptions(TypedDict, total=False):
    """What one request may say beside its method and path (see ``BaseClient.send``)."""

    params: Mapping[str, Any] | None
    json: Any
    content: bytes | FileBody | Iterable[bytes] | None
    content_sha256: str | None
    headers: Mapping[str, str] | None
    signed: bool | None
    idempotent: bool | None
    stream: bool


class BaseClient(Closeable):
    """One service endpoint: an httpx client with signing, retries and the SDK's errors.

    ``send`` is the one place a request goes out. A retried signed request is signed again
    with a fresh nonce, since the service remembers nonces. Streaming bodies (iterables) are
    sent once and never retried: they cannot be replayed; a :class:`FileBody` can.
    """

    default_service: ClassVar[str | None] = None
    """The service a subclass talks to; with no ``base_url`` its ``ROBOCLOUD_*_URL`` is used."""

    def __init__(
        self,
        base_url: str | None = None,
        identity: Identity | None = None,
        *,
        service: str | None = None,
        timeout: float = 30.0,
        retries: int = 3,
        backoff_s: float = 0.2,
        max_answer_bytes: int = MAX_ANSWER_BYTES,
        transport: httpx.BaseTransport | None = None,
        deployment: str | None = None,
        answer_deadline_s: float | None = None,
        low_speed: LowSpeed = LowSpeed(),
    ) -> None:
        self.service = service or self.default_service
        if base_url is None:
            if self.service is None:
                raise ConfigurationError(f"{type(self).__name__} needs a base URL")
            base_url = service_url(self.service)
        self.base_url = _checked_url(base_url, self.service)
        self.identity = identity
        self.retry = RetryPolicy(retries=retries, backoff_s=backoff_s)
        self.max_answer_bytes = max_answer_bytes
        self.answer_deadline_s = (
            ANSWER_DEADLINE_FACTOR * timeout if answer_deadline_s is None else answer_deadline_s
        )
        """How long an answer may take, from the request's last byte to the answer's (the
        status line and headers of a streamed answer, a whole answer otherwise)."""
        self.low_speed = low_speed
        """The slowest a streamed answer's body may come (a deadline cannot fit a body whose
        size only its reader bounds)."""
        self.deployment = deployment or expected_deployment()
        """The deployment whose audience alone this client signs for (None: what it claims)."""
        self._audience: str | None = None
        self._http = httpx.Client(
            base_url=self.base_url,
            timeout=timeout,
            transport=transport or transport_for(self.base_url),
            headers={"User-Agent": USER_AGENT, "Accept-Encoding": "identity"},
        )

    def close(self) -> None:
        self._http.close()

    def send(self, method: str, path: str, **options: Unpack[RequestOptions]) -> httpx.Response:
        """Send one request (retrying what is safe) and return the response, whatever its status.

        ``signed`` defaults to signing every method but GET, HEAD and OPTIONS; ``idempotent``
        to RFC 9110's idempotent methods (a POST that only reads may say so). Without
        ``stream`` the answer is read whole, at most ``max_answer_bytes`` within
        ``answer_deadline_s`` (``TransportTimeoutError`` past it); with it the caller reads
        and closes it (use it as a context manager), except an error answer (status 400 or
        more), which is always read. A streamed answer's headers have the same deadline; its
        body has ``timeout`` per read and ``low_speed`` as a whole (its reader bounds its
        size: ``Cas.get_to_file``), past which its reader gets ``TransportTimeoutError``
        from within ``translate_errors``.
        """
        response, _ = self._send_counting(method, path, **options)
        return response

    def _send_counting(
        self,
        method: str,
        path: str,
        *,
        params: Mapping[str, Any] | None = None,
        json: Any = None,
        content: bytes | FileBody | Iterable[bytes] | None = None,
        content_sha256: str | None = None,
        headers: Mapping[str, str] | None = None,
        signed: bool | None = None,
        idempotent: bool | None = None,
        stream: bool = False,
    ) -> tuple[httpx.Response, int]:
        """``send``, also saying how many attempts it took (a resend may have doubled a write)."""
        method = method.upper()
        must_sign = method not in _UNSIGNED_METHODS if signed is None else signed
        if idempotent is None:
            idempotent = method in IDEMPOTENT_METHODS
        send_headers = dict(headers or {})
        if json is not None:
            content = jsonlib.dumps(json, separators=(",", ":")).encode()
            send_headers.setdefault("Content-Type", "application/json")
        if isinstance(content, bytes):
            content_sha256 = hashlib.sha256(content).hexdigest()
        elif isinstance(content, FileBody):
            content_sha256 = content_sha256 or content.sha256()
            send_headers["Content-Length"] = str(content.size)
        elif content is None:
            content_sha256 = EMPTY_SHA256
        elif must_sign and content_sha256 is None:
            raise ValueError("a streamed signed body needs its content_sha256 computed beforehand")
        replayable = content is None or isinstance(content, bytes | FileBody)
        attempts = self.retry.retries + 1 if replayable else 1
        if isinstance(content, bytes) and len(content) > BODY_SLICE_BYTES:
            send_headers["Content-Length"] = str(len(content))
        for attempt in range(1, attempts + 1):
            request = self._http.build_request(
                method, path, params=params, content=_sliced(content), headers=send_headers
            )
            if must_sign:
                self._sign(request, content_sha256 or EMPTY_SHA256)
            try:
                response = self._exchange(request, stream)
            except TransportError as exc:
                if attempt < attempts and _resent_after(exc, idempotent):
                    time.sleep(self.retry.delay(attempt - 1))
                    continue
                raise
            if attempt < attempts and self._retried(response, idempotent):
                response.close()
                time.sleep(self.retry.delay(attempt - 1, response.headers.get("retry-after")))
                continue
            return response, attempt
        raise AssertionError("unreachable: the last attempt returns or raises")

    def _retried(self, response: httpx.Response, idempotent: bool) -> bool:
        """Whether the request is sent again after ``response``: 503 says the service did
        nothing, and so does a 429 that asks to come back within the policy's patience; 502
        and 504 (a proxy) leave that open, so only an idempotent request is resent."""
        status = response.status_code
        if status == 429:
            wait = retry_after_seconds(response.headers.get("retry-after"))
            return wait is not None and 0 <= wait <= self.retry.max_delay_s
        return status == 503 or (idempotent and status in (502, 504))

    def _exchange(self, request: httpx.Request, stream: bool) -> httpx.Response:
        """One request and, unless streamed, its whole answer; httpx failures translated."""
        clock = AnswerClock(self.answer_deadline_s)
        try:
            with (
                self.translate_errors(request.method, str(request.url)),
                reads_bounded_by(clock),
            ):
                response = self._http.send(request, stream=True)
                self._refuse_encoded(response)
                if stream and response.status_code < 400:
                    if isinstance(response.stream, httpx.SyncByteStream):
                        response.stream = LowSpeedGuard(response.stream, self.low_speed)
                    return response
                try:
                    limit = MAX_ERROR_BYTES if stream else self.max_answer_bytes
                    return self._read_whole(response, limit, clock)
                finally:
                    response.close()
        except TransportTimeoutError as exc:
            if clock.left_s > 0 or isinstance(exc, AnswerDeadlineError):
                raise
            raise self._past_deadline(request) from exc

    def _refuse_encoded(self, response: httpx.Response) -> None:
        """Refuse an answer with a content coding, which the request did not accept: httpx
        would decode it a whole read at a time, so 64 KiB of zstd would become gigabytes
        before ``max_answer_bytes`` or a download's cap saw one byte of it."""
        coding = response.headers.get("content-encoding", "identity").strip().lower()
        if coding != "identity":
            response.close()
            raise self._invalid(
                response, f"an answer with Content-Encoding {coding[:40]!r}, not asked for"
            )

    def _read_whole(
        self, response: httpx.Response, limit: int, clock: AnswerClock
    ) -> httpx.Response:
        """The response with its body read, refusing more than ``limit`` bytes as they arrive
        and giving up when ``clock`` runs out (the transport's reads end then; a transport of
        the caller's own is checked between reads, so at most one read's timeout late)."""
        declared = response.headers.get("content-length", "")
        if declared.isdigit() and int(declared) > limit:
            raise self._invalid(response, f"an answer of {declared} bytes, over {limit}")
        body = bytearray()
        self._check_deadline(response, clock)
        for chunk in response.iter_bytes():
            body += chunk
            if len(body) > limit:
                raise self._invalid(response, f"an answer of more than {limit} bytes")
            self._check_deadline(response, clock)
        kept = [
            (name, value)
            for name, value in response.headers.raw
            if name.lower() not in (b"content-encoding", b"content-length", b"transfer-encoding")
        ]
        return httpx.Response(
            response.status_code,
            headers=kept,
            content=bytes(body),
            request=response.request,
            extensions=response.extensions,
        )

    def _check_deadline(self, response: httpx.Response, clock: AnswerClock) -> None:
        if clock.left_s < 0:
            raise self._past_deadline(response.request)

    def _past_deadline(self, request: httpx.Request) -> AnswerDeadlineError:
        return AnswerDeadlineError(
            f"{request.method} {request.url} timed out: the answer was not complete "
            f"{self.answer_deadline_s:g} s after the request",
            method=request.method,
            url=str(request.url),
            service=self.service,
        )

    @contextmanager
    def translate_errors(self, method: str, url: str) -> Iterator[None]:
        """Turn httpx's exceptions into the SDK's, naming the service and URL.

        Streamed answers are read by the typed clients, so they read inside this too.
        """
        try:
            yield
        except (httpx.ConnectError, httpx.ConnectTimeout, httpx.UnsupportedProtocol) as exc:
            raise ConnectError(
                f"cannot connect to {self._where()}: {_reason(exc)}",
                method=method,
                url=url,
                service=self.service,
            ) from exc
        except httpx.TimeoutException as exc:
            raise TransportTimeoutError(
                f"{method} {url} timed out ({_reason(exc)})",
                method=method,
                url=url,
                service=self.service,
            ) from exc
        except httpx.DecodingError as exc:
            raise InvalidAnswerError(
                f"{self._where()} sent an undecodable answer to {method}: {exc}"
            ) from exc
        except httpx.RequestError as exc:
            raise TransportError(
                f"{method} {url} failed: {_reason(exc)}",
                method=method,
                url=url,
                service=self.service,
            ) from exc

    def json_of(self, response: httpx.Response) -> Any:
        """The answer's JSON, parsed with the SDK's nesting bound (a stranger wrote it)."""
        try:
            return bounded_json.loads(response.content)
        except FormatError as exc:
            raise self._invalid(response, f"an answer that is not usable JSON ({exc})") from exc

    def raise_for_status(self, response: httpx.Response) -> None:
        """Raise the ``ApiError`` of an error status, and ``RedirectError`` for a 3xx."""
        if response.status_code >= 400:
            raise api_error(response)
        if response.status_code >= 300:
            response.close()
            location = response.headers.get("location")
            where = f", to {location[:200]!r}" if location is not None else ""
            raise RedirectError(
                f"{self._where()} redirected {response.request.method} "
                f"{response.request.url.path} ({response.status_code}{where}); the SDK follows "
                "no redirect, so nothing was done",
                response.status_code,
                location,
            )

    def _invalid(self, response: httpx.Response, what: str) -> InvalidAnswerError:
        request = response.request
        request_id = response.headers.get("x-request-id")
        tag = f" (request id {request_id})" if request_id else ""
        return InvalidAnswerError(
            f"{self._where()} sent {what} to {request.method} {request.url.path}{tag}"
        )

    def _where(self) -> str:
        name = f"the {self.service} service" if self.service else "the service"
        return f"{name} at {self.base_url}"

    def audience(self) -> str:
        """The service's audience, ``GET /v1/audience``, fetched once per client.

        Every signature names it (ROBOCLOUD-REQUEST-V2), so a request signed for this service
        is refused by every other service and deployment. With ``deployment`` set, a service
        claiming another deployment's audience gets :class:`AudienceError` and no signature.
        """
        if self._audience is None:
            answer = self.send("GET", "/v1/audience", signed=False)
            self.raise_for_status(answer)
            self._audience = str(audience_from_answer(answer.content, self.deployment))
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


class ServiceClient(BaseClient):
    """A robocloud REST service: error statuses become typed ``ApiError``s."""

    def request(self, method: str, path: str, **options: Unpack[RequestOptions]) -> httpx.Response:
        """``send``, raising the ``ApiError`` subclass of an error status and
        ``RedirectError`` for a redirect: only a 2xx answer is a success."""
        response = self.send(method, path, **options)
        self.raise_for_status(response)
        return response

    def get_json(self, path: str, **kwargs: Any) -> Any:
        return self.json_of(self.request("GET", path, **kwargs))

    def post_json(self, path: str, body: Any = None, **kwargs: Any) -> Any:
        response = self.request("POST", path, json=body, **kwargs)
        return self.json_of(response) if response.content else None


def api_error(response: httpx.Response) -> ApiError:
    """The typed ``ApiError`` for an error answer (already read), with the service's fields.

    An answer without the JSON error model (a proxy's HTML page) still becomes the status's
    class, with the reason phrase as message.
    """
    code, message, request_id = "http_error", response.reason_phrase, None
    details: dict[str, Any] = {}
    try:
        body = bounded_json.loads(response.content)
    except FormatError:
        body = None
    if isinstance(body, dict) and isinstance(body.get("error"), dict):
        error = body["error"]
        code = str(error.get("code", code))
        message = str(error.get("message", message))
        found = error.get("details")
        details = found if isinstance(found, dict) else {}
        request_id = error.get("request_id")
    request_id = str(request_id or response.headers.get("x-request-id") or "") or None
    if response.status_code == 429 and "retry_after" not in details:
        retry_after = response.headers.get("retry-after")
        if retry_after is not None:
            details = {**details, "retry_after": retry_after}
    return error_class_for(response.status_code)(
        response.status_code, code, message, details, request_id
    )


def _resent_after(error: TransportError, idempotent: bool) -> bool:
    """Whether a request is sent again after ``error``: always when it never left, when it
    may have arrived only if resending is harmless, and never after a dripped answer."""
    if isinstance(error, AnswerDeadlineError):
        return False
    return isinstance(error, ConnectError) or idempotent


def _reason(exc: httpx.RequestError) -> str:
    text = str(exc).strip()
    return text or type(exc).__name__


def _sliced(
    content: bytes | FileBody | Iterable[bytes] | None,
) -> bytes | Iterable[bytes] | None:
    """A large bytes body as slices (``BODY_SLICE_BYTES``), new ones for each attempt; its
    ``Content-Length`` is set by the caller, so it is not sent chunked."""
    if not isinstance(content, bytes) or len(content) <= BODY_SLICE_BYTES:
        return content
    whole = memoryview(content)
    return (
        bytes(whole[start : start + BODY_SLICE_BYTES])
        for start in range(0, len(whole), BODY_SLICE_BYTES)
    )
