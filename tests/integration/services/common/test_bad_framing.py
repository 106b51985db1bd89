"""Requests h11 cannot frame, over a bare socket to a real service: each is answered in the
services' JSON error model (``bad_http_request``, h11's reason, a request id) and the
connection closed, not with uvicorn's plain-text "Invalid HTTP request received."."""

from __future__ import annotations

import json
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.procs import ServiceProcess
from tests.raw_http import drain


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One service for the module: every request here is refused before any route runs."""
    with ServiceProcess("fl", Path(tmp_path_factory.mktemp("framing")) / "fl") as process:
        yield process


def refused(service: ServiceProcess, request: bytes) -> tuple[int, dict[str, str], dict[str, Any]]:
    """Status, headers and JSON body of the answer to ``request``; ``drain`` returns only
    once the service closed the connection (it fails after 10 s otherwise)."""
    with socket.create_connection(("127.0.0.1", service.port)) as sock:
        sock.sendall(request)
        received = drain(sock)
    head, _, body = received.partition(b"\r\n\r\n")
    status_line, *lines = head.decode().split("\r\n")
    headers = dict(line.lower().split(": ", 1) for line in lines)
    assert len(body) == int(headers["content-length"]), "one answer, then the close"
    return int(status_line.split()[1]), headers, json.loads(body)


HEAD = b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\n"


@pytest.mark.parametrize(
    ("request_bytes", "status", "reason"),
    [
        (HEAD + b"Content-Length: abc\r\n\r\n", 400, "bad Content-Length"),
        (
            HEAD + b"Content-Length: 1\r\nContent-Length: 2\r\n\r\n",
            400,
            "conflicting Content-Length headers",
        ),
        (
            HEAD + b"Transfer-Encoding: gzip\r\n\r\n",
            501,
            "Only Transfer-Encoding: chunked is supported",
        ),
        (HEAD + b"Transfer-Encoding: chunked\r\n\r\nzz\r\nab\r\n", 400, "illegal chunk header"),
        (b"GET /healthz HTTP/1.1\r\n\r\n", 400, "Missing mandatory Host: header"),
        (HEAD + b"Bad Name: v\r\n\r\n", 400, "illegal header line"),
    ],
    ids=["content-length-abc", "two-content-lengths", "gzip", "chunk-size", "no-host", "space"],
)
def test_badly_framed_request_is_a_json_error_and_the_connection_closes(
    service: ServiceProcess, request_bytes: bytes, status: int, reason: str
) -> None:
    answered, headers, body = refused(service, request_bytes)
    assert answered == status
    assert headers["content-type"] == "application/json"
    assert headers["connection"] == "close"
    error = body["error"]
    assert error["code"] == "bad_http_request"
    assert reason in error["message"]
    assert error["request_id"] == headers["x-request-id"]


def test_the_reason_quoted_is_bounded_and_printable(service: ServiceProcess) -> None:
    """h11's reason quotes the offending line; a long one of raw bytes comes back cut short
    and as printable ASCII."""
    line = b"Bad Name: " + bytes(range(128, 256)) * 40
    answered, _, body = refused(service, HEAD + line + b"\r\n\r\n")
    message = body["error"]["message"]
    assert answered == 400
    assert "illegal header line" in message
    assert len(message) < 300
    assert message.isascii()
    assert message.isprintable()
