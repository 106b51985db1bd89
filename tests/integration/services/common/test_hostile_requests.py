"""Requests meant to freeze or crash a service, against a real process: refused, service up.

A request head is bounded in the server itself (431 for the head, 414 for the request line),
as soon as the bytes that break the bound arrive; a deeply nested JSON body is 400 and the
process runs with a recursion limit its C stack can hold.
"""

from __future__ import annotations

import hashlib
import json
import select
import socket
from typing import Any

import httpx
import pytest

from robocloud.identity import Identity
from robocloud.signing import sign_request
from tests.conftest import ServiceFactory
from tests.procs import ServiceProcess, memory_kib
from tests.raw_http import read_answer

MiB = 1 << 20
HEADER_LIMIT = 64 * 1024
LINE_LIMIT = 8 * 1024


def stream_until_answered(sock: socket.socket, total: int) -> tuple[int, int, dict[str, Any]]:
    """Send up to ``total`` bytes of header value; stop when the service answers or hangs up.

    Returns the bytes sent, and the answer's status and body.
    """
    sock.setblocking(False)
    chunk = b"a" * 65536
    sent = 0
    received = b""
    while sent < total:
        readable, writable, _ = select.select([sock], [sock], [], 30)
        if readable:
            data = sock.recv(65536)
            received += data
            if not data or b"\r\n\r\n" in received:
                break
        elif writable:
            try:
                sent += sock.send(chunk)
            except (BrokenPipeError, ConnectionResetError):
                break
        else:
            pytest.fail("the service neither read nor answered for 30 s")
    status, answer = read_answer(sock, received)
    return sent, status, answer


@pytest.fixture
def storage(service_factory: ServiceFactory) -> ServiceProcess:
    return service_factory("storage")


def healthz(service: ServiceProcess) -> dict[str, Any]:
    answer: dict[str, Any] = httpx.get(f"{service.url}/healthz", timeout=10).json()
    return answer


def test_200_mib_header_is_cut_off_with_431_and_the_service_stays_responsive(
    storage: ServiceProcess,
) -> None:
    peak_before = memory_kib(storage)["VmHWM"]
    attackers = [socket.create_connection(("127.0.0.1", storage.port)) for _ in range(10)]
    try:
        for sock in attackers:
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 60_000)
        assert healthz(storage)["status"] == "ok", "partial heads held open stall nobody"
        sent, status, answer = stream_until_answered(attackers[0], 200 * MiB)
    finally:
        for sock in attackers:
            sock.close()
    assert status == 431
    assert answer["error"]["code"] == "headers_too_large"
    assert answer["error"]["details"] == {"limit": HEADER_LIMIT}
    assert sent < 32 * MiB, f"refused after {sent} bytes, not at the limit"
    growth_kib = memory_kib(storage)["VmHWM"] - peak_before
    assert growth_kib < 32 * 1024, f"peak memory grew by {growth_kib} KiB"
    assert healthz(storage)["status"] == "ok"


def test_100_kb_url_is_414_naming_the_limit(storage: ServiceProcess) -> None:
    with socket.create_connection(("127.0.0.1", storage.port)) as sock:
        sock.sendall(b"GET /" + b"a" * 100_000)
        status, answer = read_answer(sock)
    assert status == 414
    assert answer["error"]["code"] == "request_line_too_long"
    assert answer["error"]["details"] == {"limit": LINE_LIMIT}
    assert healthz(storage)["status"] == "ok"


def test_heads_within_the_limit_are_served_on_a_kept_alive_connection(
    storage: ServiceProcess,
) -> None:
    """The bound is per request head: each request on a connection is counted afresh."""
    big_header = b"X-Big: " + b"a" * 60_000 + b"\r\n"
    request = b"GET /healthz HTTP/1.1\r\nHost: x\r\n" + big_header + b"\r\n"
    with socket.create_connection(("127.0.0.1", storage.port)) as sock:
        for _ in range(3):
            sock.sendall(request)
            status, answer = read_answer(sock)
            assert (status, answer["status"]) == (200, "ok")
        sock.sendall(request.replace(b"a" * 60_000, b"a" * 70_000))
        status, answer = read_answer(sock)
    assert (status, answer["error"]["code"]) == (431, "headers_too_large")


def test_limits_are_the_services_settings(service_factory: ServiceFactory) -> None:
    service = service_factory(
        "fl", {"ROBOCLOUD_MAX_HEADER_BYTES": "4096", "ROBOCLOUD_MAX_REQUEST_LINE_BYTES": "1024"}
    )
    assert httpx.get(f"{service.url}/healthz", headers={"X-A": "a" * 3000}).status_code == 200
    too_big = httpx.get(f"{service.url}/healthz", headers={"X-A": "a" * 5000})
    assert too_big.status_code == 431
    assert too_big.json()["error"]["details"] == {"limit": 4096}
    too_long = httpx.get(f"{service.url}/healthz?q=" + "b" * 2000)
    assert too_long.status_code == 414
    assert too_long.json()["error"]["details"] == {"limit": 1024}


def test_head_dribbled_a_byte_at_a_time_is_cut_off_with_408(
    service_factory: ServiceFactory,
) -> None:
    """Slowloris: each byte arrives well within any idle timeout, the head never completes."""
    service = service_factory("broker", {"ROBOCLOUD_HEADER_TIMEOUT_S": "1"})
    with socket.create_connection(("127.0.0.1", service.port)) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        answered = False
        for _ in range(300):  # 60 s at most; the service cuts it off after 1 s
            if select.select([sock], [], [], 0.2)[0]:
                answered = True
                break
            sock.sendall(b"X")
        assert answered, "the service never cut the slow head off"
        status, answer = read_answer(sock)
    assert status == 408
    assert answer["error"]["code"] == "header_timeout"
    assert answer["error"]["details"] == {"limit_s": 1.0}
    assert healthz(service)["status"] == "ok"


@pytest.mark.parametrize(("trusted", "client"), [("", "127.0.0.1"), ("127.0.0.1", "198.51.100.7")])
def test_the_client_is_the_peer_address_unless_a_trusted_proxy_names_another(
    service_factory: ServiceFactory, trusted: str, client: str
) -> None:
    """Who asks is what the shares of costly turns count. uvicorn believed X-Forwarded-For
    from loopback by default, so a local client could claim a new address each request."""
    service = service_factory("broker", {"ROBOCLOUD_TRUSTED_PROXIES": trusted})
    headers = {"X-Forwarded-For": "198.51.100.7", "X-Request-Id": "forwarded-for"}
    assert httpx.get(f"{service.url}/healthz", headers=headers).json()["status"] == "ok"
    (line,) = service.logged(lambda line: line.get("request_id") == "forwarded-for")
    assert (line["path"], line["client"]) == ("/healthz", client)


def test_kept_alive_connection_is_not_timed_out_between_quick_requests(
    service_factory: ServiceFactory,
) -> None:
    """The head deadline starts with a head's first byte and ends with its last."""
    service = service_factory("broker", {"ROBOCLOUD_HEADER_TIMEOUT_S": "1"})
    with socket.create_connection(("127.0.0.1", service.port)) as sock:
        for _ in range(3):
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            assert read_answer(sock) == (200, healthz(service))
            select.select([], [], [], 0.7)  # together longer than the deadline, each shorter


def test_100000_deep_json_body_is_400_and_the_service_stays_up(
    storage: ServiceProcess, identity: Identity
) -> None:
    """200 KB of brackets: the depth is measured without recursion (on a worker thread, past
    64 KiB), and the process runs with the recursion limit CPython's C stack is sized for,
    not py_ecc's 100,000. Sent to a route that takes 256 KiB: ``/v1/whoami`` takes 64 KiB."""
    body = b"[" * 100_000 + b"]" * 100_000
    digest = hashlib.sha256(body).hexdigest()
    headers = sign_request(identity.account, storage.audience, "POST", "/v1/templates", "", digest)
    response = httpx.post(
        f"{storage.url}/v1/templates",
        content=body,
        headers={**headers, "Content-Type": "application/json"},
        timeout=30,
    )
    assert response.status_code == 400
    error = response.json()["error"]
    assert error["code"] == "json_too_deep"
    assert error["details"]["max_depth"] <= 64  # the templates' own bound, within the services'
    assert storage.process is not None
    assert storage.process.poll() is None
    assert healthz(storage)["status"] == "ok"
    assert serving_line(storage)["recursion_limit"] == 1000


def serving_line(service: ServiceProcess) -> dict[str, Any]:
    """The runner's ``serving`` log line: the limits the process actually runs with."""
    for line in service.log().splitlines():
        if line.startswith("{") and json.loads(line).get("msg") == "serving":
            entry: dict[str, Any] = json.loads(line)
            return entry
    raise AssertionError(f"no serving line in the log of {service.name}")


@pytest.mark.parametrize(("service", "path"), [("storage", "/v1/whoami"), ("ledger", "/v1/faucet")])
def test_a_route_of_a_few_fields_refuses_a_large_body_before_reading_it(
    service_factory: ServiceFactory, identity: Identity, service: str, path: str
) -> None:
    """Its body was read, checked and parsed whole on the event loop: 16 MiB of nested
    arrays held the ledger 8 s, ``/healthz`` included."""
    started = service_factory(service)
    body = b"[" * 40 + b"0," * 40_000 + b"0" + b"]" * 40
    digest = hashlib.sha256(body).hexdigest()
    headers = sign_request(identity.account, started.audience, "POST", path, "", digest)
    response = httpx.post(
        f"{started.url}{path}",
        content=body,
        headers={**headers, "Content-Type": "application/json"},
        timeout=30,
    )
    assert response.status_code == 413, response.text
    error = response.json()["error"]
    assert error["code"] == "payload_too_large"
    assert "65536" in error["message"]
