"""Streams are bounded: answers in number (stream turns) and in how long a client that stops
reading may hold one (the send timeout), bodies in how long one may pause (the body timeout)."""

from __future__ import annotations

import hashlib
import os
import socket
import time
from contextlib import ExitStack

import httpx
import pytest

from robocloud.cas import Cas
from robocloud.identity import Identity
from robocloud.signing import sign_request
from tests.conftest import ServiceFactory
from tests.integration.services.cas.conftest import QUIET_GC, multipart, store_unchanged
from tests.procs import ServiceProcess
from tests.raw_http import drain, read_answer, stalled_reader

SEND_TIMEOUT_S = 8
"""Longer than the 5 s a stream waits for a turn, so the refusal comes while both are held."""
FILE_BYTES = 64 << 20
"""Far more than loopback's socket buffers take in while nobody reads."""


@pytest.fixture
def cas_service(service_factory: ServiceFactory) -> ServiceProcess:
    env = {
        **QUIET_GC,
        "ROBOCLOUD_CAS_MAX_STREAMS": "2",
        "ROBOCLOUD_SEND_TIMEOUT_S": str(SEND_TIMEOUT_S),
    }
    return service_factory("cas", env)


def test_stalled_readers_hold_their_turns_only_until_the_send_timeout(
    cas_service: ServiceProcess,
) -> None:
    content = os.urandom(FILE_BYTES)
    with Cas(cas_service.url, Identity.generate()) as cas:
        cid = cas.add_bytes(content)
        small = cas.add_bytes(b"five!")
    heads = [
        f"GET /ipfs/{cid} HTTP/1.1\r\nHost: cas\r\nX-Request-Id: stalled-gateway\r\n\r\n",
        f"POST /api/v0/dag/export?arg={cid} HTTP/1.1\r\nHost: cas\r\nContent-Length: 0\r\n"
        "X-Request-Id: stalled-export\r\n\r\n",
    ]
    with ExitStack() as stack:
        started = time.monotonic()
        stalled = [
            stack.enter_context(stalled_reader(cas_service, head.encode(), client))
            for head, client in zip(heads, ("127.0.0.2", "127.0.0.3"), strict=True)
        ]
        time.sleep(0.5)
        busy = httpx.post(f"{cas_service.url}/api/v0/cat", params={"arg": str(cid)}, timeout=30)
        refused_after = time.monotonic() - started
        ready = httpx.get(f"{cas_service.url}/readyz", timeout=5)
        # A read that fits in one batch is answered whole and needs no turn.
        small_read = httpx.get(f"{cas_service.url}/ipfs/{small}", timeout=5)
        small_cat = httpx.post(f"{cas_service.url}/api/v0/cat", params={"arg": str(small)})
        # Reading before the timeout would resume the streams; read after it.
        time.sleep(max(0.0, started + SEND_TIMEOUT_S + 2 - time.monotonic()))
        cut = [drain(connection) for connection in stalled]
    assert busy.status_code == 503
    assert busy.headers["retry-after"] == "1"
    assert busy.json()["error"]["code"] == "busy"
    assert busy.json()["error"]["message"] == (
        "all 2 stream slots stayed busy for 5 s; retry later"
    )
    assert 5 <= refused_after < SEND_TIMEOUT_S
    assert ready.json()["status"] == "ready"
    assert (small_read.status_code, small_read.content) == (200, b"five!")
    assert (small_cat.status_code, small_cat.content) == (200, b"five!")
    # Each stalled client got a head and part of the body, then the connection closed.
    for answer in cut:
        assert answer.startswith(b"HTTP/1.1 200 OK\r\n")
        assert len(answer) < FILE_BYTES

    whole = httpx.get(f"{cas_service.url}/ipfs/{cid}", timeout=30)
    assert hashlib.sha256(whole.content).digest() == hashlib.sha256(content).digest()
    dropped = cas_service.logged(
        lambda line: line.get("msg") == "client stopped reading; connection dropped", count=2
    )
    log = cas_service.log()
    assert sorted((line["request_id"], line["path"]) for line in dropped) == [
        ("stalled-export", "/api/v0/dag/export"),
        ("stalled-gateway", f"/ipfs/{cid}"),
    ]
    assert '"level": "error"' not in log


def test_one_client_stalling_streams_holds_only_its_share_of_the_turns(
    cas_service: ServiceProcess,
) -> None:
    """Before the shares, one client's stalled downloads held every turn until the send
    timeout, and every other client's download was refused."""
    content = os.urandom(FILE_BYTES)
    with Cas(cas_service.url, Identity.generate()) as cas:
        cid = cas.add_bytes(content)
    head = f"GET /ipfs/{cid} HTTP/1.1\r\nHost: cas\r\n\r\n".encode()
    # The client named in X-Forwarded-For is not believed, from loopback either (uvicorn's
    # default): the peer address is the client.
    forwarded = f"GET /ipfs/{cid} HTTP/1.1\r\nHost: cas\r\nX-Forwarded-For: 198.51.100.7\r\n\r\n"
    with ExitStack() as stack:
        stack.enter_context(stalled_reader(cas_service, head))
        time.sleep(0.5)
        started = time.monotonic()
        second = stack.enter_context(stalled_reader(cas_service, forwarded.encode()))
        status, refusal = read_answer(second)
        refused_after = time.monotonic() - started
        other_client = httpx.HTTPTransport(local_address="127.0.0.2")
        with httpx.Client(transport=other_client, timeout=30) as client:
            other = client.get(f"{cas_service.url}/ipfs/{cid}")
    assert status == 429
    error = refusal["error"]
    assert error["code"] == "rate_limited"
    assert error["message"] == (
        "this client already holds 1 of the 2 stream slots, its share, and none came free in "
        "5 s; retry later"
    )
    assert error["details"] == {"share": 1, "slots": 2, "wait_s": 5.0}
    assert 5 <= refused_after < SEND_TIMEOUT_S
    assert other.status_code == 200
    assert hashlib.sha256(other.content).digest() == hashlib.sha256(content).digest()
    (line,) = cas_service.logged(lambda line: line.get("status") == 429)
    assert (line["client"], line["path"]) == ("127.0.0.1", f"/ipfs/{cid}")


def test_an_upload_that_stops_half_way_is_answered_408_and_nothing_is_stored(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    service = service_factory("cas", {**QUIET_GC, "ROBOCLOUD_BODY_TIMEOUT_S": "1"})
    body, content_type = multipart(("stalled.bin", os.urandom(1 << 20)))
    digest = hashlib.sha256(body).hexdigest()
    signed = sign_request(identity.account, service.audience, "POST", "/api/v0/add", "", digest)
    head = "".join(f"{name}: {value}\r\n" for name, value in signed.items())
    packs_before = packs(service)
    with store_unchanged(service), socket.create_connection(("127.0.0.1", service.port)) as sock:
        sock.sendall(
            f"POST /api/v0/add HTTP/1.1\r\nHost: cas\r\nX-Request-Id: stalled-upload\r\n"
            f"Content-Type: {content_type}\r\nContent-Length: {len(body)}\r\n{head}\r\n".encode()
            + body[: len(body) // 2]
        )
        started = time.monotonic()
        status, answer = read_answer(sock)
        answered_after = time.monotonic() - started
        closed = sock.recv(1) == b""
    assert (status, closed) == (408, True)
    assert answer["error"] == {
        "code": "body_timeout",
        "message": "the request body stopped arriving for 1 s",
        "details": {"limit_s": 1.0},
        "request_id": "stalled-upload",
    }
    assert 1 <= answered_after < 10
    assert packs(service) == packs_before
    lines = service.logged(lambda line: line.get("request_id") == "stalled-upload", count=2)
    # The server's line, and the access log's: the status the client got, not 499.
    assert [(line["msg"], line["path"], line["status"]) for line in lines] == [
        ("request refused", "/api/v0/add", 408),
        ("request", "/api/v0/add", 408),
    ]


def packs(service: ServiceProcess) -> list[str]:
    """The pack files on disk: an upload stages its blocks into a new one."""
    return sorted(path.name for path in (service.data_dir / "packs").iterdir())
