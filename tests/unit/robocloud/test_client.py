"""The base client against real sockets: what it retries, what it refuses, what it raises.

Every failure must come out as an SDK error (never an httpx exception), every answer is read
within bounds, and a hostile answer nested 100,000 deep is an error, not a crash (this test
process has py_ecc's raised recursion limit, so an unbounded parse would kill it).
"""

from __future__ import annotations

import hashlib
import os
import threading
from pathlib import Path

import httpx
import pytest
import zstandard

from robocloud.bounded_json import JsonDepthError
from robocloud.client import (
    BODY_SLICE_BYTES,
    FILE_BODY_CHUNK,
    BaseClient,
    FileBody,
    RetryPolicy,
    ServiceClient,
)
from robocloud.errors import (
    AuthenticationError,
    ConfigurationError,
    ConnectError,
    InvalidAnswerError,
    MissingIdentityError,
    NotFoundError,
    RateLimitedError,
    RobocloudError,
    ServerError,
    TransportError,
    TransportTimeoutError,
    UnavailableError,
)
from robocloud.identity import Identity
from robocloud.signing import HEADER_CONTENT_SHA256, HEADER_NONCE
from tests.procs import free_port
from tests.scripted_http import (
    Exchange,
    Reply,
    Script,
    json_reply,
    nested_json,
    scripted_client,
)

FAST = {"backoff_s": 0.001}


def test_an_unreachable_service_is_a_connect_error_naming_service_and_url() -> None:
    url = f"http://127.0.0.1:{free_port()}"
    with ServiceClient(url, service="cas", **FAST) as client, pytest.raises(ConnectError) as err:
        client.request("POST", "/api/v0/pin/ls", signed=False)
    assert err.value.service == "cas"
    assert err.value.url == f"{url}/api/v0/pin/ls"
    assert f"the cas service at {url}" in str(err.value)
    assert isinstance(err.value.__cause__, httpx.ConnectError)


def test_503_is_retried_with_a_fresh_nonce_until_it_succeeds() -> None:
    answers = iter([json_reply("{}", 503), json_reply("{}", 503), json_reply('{"ok":true}')])
    robot = Identity.generate()
    with scripted_client(lambda _: next(answers), identity=robot, **FAST) as (server, client):
        assert client.post_json("/v1/write", {"x": 1}) == {"ok": True}
    nonces = [exchange.headers[HEADER_NONCE.lower()] for exchange in server.exchanges]
    assert len(nonces) == 3
    assert len(set(nonces)) == 3


def test_503_after_the_last_retry_is_an_unavailable_error_with_the_service_fields() -> None:
    error = b'{"error":{"code":"not_ready","message":"warm","details":{},"request_id":"r1"}}'
    script = lambda _: json_reply(error, 503)  # noqa: E731
    with (
        scripted_client(script, retries=2, **FAST) as (server, client),
        pytest.raises(UnavailableError) as err,
    ):
        client.get_json("/v1/thing")
    assert server.count() == 3
    assert (err.value.status, err.value.code, err.value.request_id) == (503, "not_ready", "r1")


def test_retry_after_is_honoured_within_the_cap() -> None:
    policy = RetryPolicy(retries=3, backoff_s=0.1, max_delay_s=5.0)
    assert policy.delay(0) == 0.1
    assert policy.delay(2) == 0.4
    assert policy.delay(0, "2") == 2.0
    assert policy.delay(0, "100000") == 5.0
    assert policy.delay(0, "soon") == 0.1
    assert policy.delay(0, "-5") == 0.1
    assert policy.delay(0, "nan") == 0.1


def dropping_first(count: int) -> Script:
    """Close the connection without answering the first ``count`` requests."""
    seen = [0]

    def script(_: Exchange) -> Reply:
        seen[0] += 1
        return None if seen[0] <= count else json_reply('{"ok":true}')

    return script


def test_a_dropped_answer_is_retried_for_a_get() -> None:
    with scripted_client(dropping_first(2), retries=3, **FAST) as (server, client):
        assert client.get_json("/v1/read") == {"ok": True}
    assert server.count() == 3


def test_a_dropped_answer_to_a_write_is_not_resent() -> None:
    """The write may have taken effect; resending it could do it twice."""
    robot = Identity.generate()
    with (
        scripted_client(dropping_first(1), identity=robot, **FAST) as (server, client),
        pytest.raises(TransportError) as err,
    ):
        client.post_json("/v1/write", {"x": 1})
    assert server.count() == 1
    assert not isinstance(err.value, ConnectError)
    assert isinstance(err.value.__cause__, httpx.RemoteProtocolError)


def test_a_post_that_only_reads_may_say_so_and_is_retried() -> None:
    with scripted_client(dropping_first(1), **FAST) as (server, client):
        response = client.request("POST", "/api/v0/pin/ls", signed=False, idempotent=True)
    assert response.json() == {"ok": True}
    assert server.count() == 2


def test_a_large_body_is_sent_whole_with_its_length_on_every_attempt() -> None:
    """A bytes body over ``BODY_SLICE_BYTES`` goes out in slices (httpcore copies what is
    left of a whole one after each send): still one ``Content-Length`` body, never chunked,
    signed for its digest, and resent whole, its slices made again, after a 503."""
    robot = Identity.generate()
    body = os.urandom(3 * BODY_SLICE_BYTES + 5)
    answers = iter([json_reply("{}", 503), json_reply('{"ok":true}')])
    with scripted_client(lambda _: next(answers), identity=robot, **FAST) as (server, client):
        assert client.request("POST", "/upload", content=body).json() == {"ok": True}
    assert [exchange.body == body for exchange in server.exchanges] == [True, True]
    for exchange in server.exchanges:
        assert exchange.headers["content-length"] == str(len(body))
        assert "transfer-encoding" not in exchange.headers
        assert exchange.headers[HEADER_CONTENT_SHA256.lower()] == hashlib.sha256(body).hexdigest()


def test_a_file_body_is_read_again_and_resent_whole(tmp_path: Path) -> None:
    """A bag's upload was an iterator, sent once: a proxy's 502 lost it for good. A
    ``FileBody`` is read anew for each attempt, with its length and digest each time."""
    robot = Identity.generate()
    body = os.urandom(2 * FILE_BODY_CHUNK + 7)
    path = tmp_path / "run.bag"
    path.write_bytes(body)
    answers = iter([json_reply("{}", 502), json_reply('{"ok":true}')])
    with scripted_client(lambda _: next(answers), identity=robot, **FAST) as (server, client):
        answered = client.request("POST", "/upload", content=FileBody(path), idempotent=True)
    assert answered.json() == {"ok": True}
    assert [exchange.body == body for exchange in server.exchanges] == [True, True]
    for exchange in server.exchanges:
        assert exchange.headers["content-length"] == str(len(body))
        assert "transfer-encoding" not in exchange.headers
        assert exchange.headers[HEADER_CONTENT_SHA256.lower()] == hashlib.sha256(body).hexdigest()
    assert len({exchange.headers[HEADER_NONCE.lower()] for exchange in server.exchanges}) == 2


def test_a_streamed_body_is_sent_once() -> None:
    robot = Identity.generate()
    script = lambda _: json_reply("{}", 503)  # noqa: E731
    with (
        scripted_client(script, identity=robot, **FAST) as (server, client),
        pytest.raises(UnavailableError),
    ):
        client.request("POST", "/upload", content=iter([b"a", b"b"]), content_sha256="0" * 64)
    assert server.count() == 1


def test_a_stalled_answer_is_a_timeout_error() -> None:
    release = threading.Event()

    def stall(_: Exchange) -> Reply:
        release.wait(30)
        return json_reply("{}")

    with scripted_client(stall, timeout=0.2, retries=0) as (_, client):
        try:
            with pytest.raises(TransportTimeoutError) as err:
                client.get_json("/slow")
        finally:
            release.set()
    assert isinstance(err.value.__cause__, httpx.ReadTimeout)


@pytest.mark.parametrize("chunked", [False, True], ids=["content-length", "chunked"])
def test_an_oversized_answer_is_refused_as_it_arrives(chunked: bool) -> None:
    body = b"[" + b"0," * 600_000 + b"0]"

    def script(_: Exchange) -> Reply:
        if not chunked:
            return json_reply(body)
        chunks = b"".join(b"%x\r\n%s\r\n" % (len(p), p) for p in (body[:600_000], body[600_000:]))
        return 200, {"Transfer-Encoding": "chunked"}, chunks + b"0\r\n\r\n"

    with (
        scripted_client(script, max_answer_bytes=1 << 20, retries=0) as (_, client),
        pytest.raises(InvalidAnswerError, match=r"(more than|over) 1048576"),
    ):
        client.get_json("/big")


def test_deeply_nested_json_is_an_invalid_answer_not_a_crash() -> None:
    script = lambda _: json_reply(nested_json(100_000))  # noqa: E731
    with (
        scripted_client(script, service="ledger", retries=0) as (_, client),
        pytest.raises(InvalidAnswerError) as err,
    ):
        client.get_json("/v1/contracts")
    assert isinstance(err.value.__cause__, JsonDepthError)
    assert "the ledger service at" in str(err.value)
    assert "GET /v1/contracts" in str(err.value)


@pytest.mark.parametrize("coding", ["zstd", "gzip", "br", "deflate", "identity, gzip"])
@pytest.mark.parametrize("stream", [False, True])
def test_a_compressed_answer_is_refused_before_a_byte_is_decoded(coding: str, stream: bool) -> None:
    """httpx decodes a whole read at a time: 64 KiB of zstd zeros became 2 GiB (4.3 GB of
    memory) before ``max_answer_bytes`` or a download's cap saw the first of them. The
    client asks for none and takes none."""
    bomb = zstandard.ZstdCompressor().compress(bytes(256 << 20))
    asked: list[str] = []

    def answer(exchange: Exchange) -> Reply:
        asked.append(exchange.headers.get("accept-encoding", ""))
        return json_reply(bomb, **{"Content-Encoding": coding})

    with (
        scripted_client(answer, retries=0) as (_, client),
        pytest.raises(InvalidAnswerError, match=f"Content-Encoding '{coding}', not asked for"),
    ):
        client.send("GET", "/x", stream=stream)
    assert asked == ["identity"]


@pytest.mark.parametrize(
    ("status", "body", "kind", "code"),
    [
        (404, b'{"error":{"code":"gone","message":"x","request_id":"q"}}', NotFoundError, "gone"),
        (
            401,
            b'{"error":{"code":"stale_timestamp","message":"clock"}}',
            AuthenticationError,
            "stale_timestamp",
        ),
        (500, b"<html>proxy error</html>", ServerError, "http_error"),
        (418, nested_json(100_000), RobocloudError, "http_error"),
        (401, b'{"error":"not an object"}', AuthenticationError, "http_error"),
    ],
    ids=["json-error", "auth", "html", "nested-error-body", "odd-shape"],
)
def test_error_answers_become_typed_api_errors(
    status: int, body: bytes, kind: type[Exception], code: str
) -> None:
    reply = json_reply(body, status, **{"X-Request-Id": "from-header"})
    with scripted_client(lambda _: reply, retries=0) as (_, client), pytest.raises(kind) as err:
        client.get_json("/x")
    assert getattr(err.value, "code", None) == code
    assert getattr(err.value, "request_id", None) in ("q", "from-header")


def test_a_429_that_asks_for_a_moment_is_retried_one_that_asks_for_longer_is_not() -> None:
    """A service refuses a client over its share of turns with 429 and ``Retry-After: 1``
    (nothing was done); a faucet's 429 asks for minutes, and the robot is told at once."""
    busy = b'{"error":{"code":"rate_limited","message":"this client already holds 1"}}'
    answers = iter([json_reply(busy, 429, **{"Retry-After": "0"}), json_reply('{"ok":true}')])
    robot = Identity.generate()
    with scripted_client(lambda _: next(answers), identity=robot, **FAST) as (server, client):
        assert client.post_json("/v1/write", {"x": 1}) == {"ok": True}
    assert server.count() == 2
    later = json_reply(busy, 429, **{"Retry-After": "3600"})
    with (
        scripted_client(lambda _: later, **FAST) as (server, client),
        pytest.raises(RateLimitedError) as err,
    ):
        client.get_json("/x")
    assert server.count() == 1
    assert err.value.retry_after == 3600.0


def test_429_carries_retry_after() -> None:
    error = b'{"error":{"code":"slow_down","message":"later"}}'
    reply = json_reply(error, 429, **{"Retry-After": "7"})
    with (
        scripted_client(lambda _: reply, retries=0) as (_, client),
        pytest.raises(RateLimitedError) as err,
    ):
        client.get_json("/x")
    assert err.value.retry_after == 7.0


@pytest.mark.parametrize(
    ("header", "details"),
    [
        ("Wed, 21 Oct 2015 07:28:00 GMT", None),
        ("soon", None),
        (None, '{"retry_after": [1]}'),
        (None, '{"retry_after": {"s": 1}}'),
        (None, '{"retry_after": true}'),
    ],
    ids=["http-date", "text", "list", "object", "bool"],
)
def test_a_retry_after_that_is_no_number_is_none(header: str | None, details: str | None) -> None:
    """An HTTP date is a valid Retry-After, and a 429's details are the service's word: the
    property raised a bare ValueError or TypeError at whoever asked how long to wait."""
    error = f'{{"error":{{"code":"slow_down","message":"later","details":{details or "{}"}}}}}'
    reply = json_reply(error, 429, **({"Retry-After": header} if header else {}))
    with (
        scripted_client(lambda _: reply, retries=0) as (_, client),
        pytest.raises(RateLimitedError) as err,
    ):
        client.get_json("/x")
    assert err.value.retry_after is None


@pytest.mark.parametrize("url", ["ftp://example.org", "example.org:8080", "http://", "http://[::1"])
def test_an_unusable_url_is_a_configuration_error(url: str) -> None:
    with pytest.raises(ConfigurationError):
        ServiceClient(url)


def test_the_default_url_comes_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    class Storage(ServiceClient):
        default_service = "storage"

    monkeypatch.setenv("ROBOCLOUD_STORAGE_URL", "http://storage.example:9000/")
    with Storage() as client:
        assert client.base_url == "http://storage.example:9000"
        assert client.service == "storage"
    with pytest.raises(ConfigurationError, match="needs a base URL"):
        BaseClient()


def test_a_write_without_identity_is_refused_before_sending() -> None:
    with (
        scripted_client(lambda _: json_reply("{}")) as (server, client),
        pytest.raises(MissingIdentityError),
    ):
        client.post_json("/v1/write", {})
    assert server.count() == 0
