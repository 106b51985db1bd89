"""HTTP over a bare socket, for what no client library does: a head dribbled a byte at a
time, a download never read, and the answers to them."""

from __future__ import annotations

import json
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from tests.procs import ServiceProcess


def read_answer(sock: socket.socket, received: bytes = b"") -> tuple[int, dict[str, Any]]:
    """Status and JSON body of one answer, read until its Content-Length is complete."""
    sock.setblocking(True)
    sock.settimeout(30)
    while b"\r\n\r\n" not in received:
        received += sock.recv(65536)
    head, _, body = received.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    headers = dict(line.lower().split(": ", 1) for line in lines[1:])
    while len(body) < int(headers["content-length"]):
        chunk = sock.recv(65536)
        assert chunk, "connection closed mid-answer"
        body += chunk
    answer: dict[str, Any] = json.loads(body)
    assert (answer.get("error") or {}).get("request_id", headers["x-request-id"]) == (
        headers["x-request-id"]
    )
    return int(lines[0].split()[1]), answer


@contextmanager
def stalled_reader(
    service: ServiceProcess, head: bytes, client: str = "127.0.0.1"
) -> Iterator[socket.socket]:
    """A connection from ``client`` (any loopback address) that sends ``head`` and then reads
    nothing. (A tiny receive buffer would leave the service's side waiting on TCP's
    zero-window probes once reading resumes.)"""
    connection = socket.create_connection(("127.0.0.1", service.port), source_address=(client, 0))
    try:
        connection.sendall(head)
        yield connection
    finally:
        connection.close()


def drain(connection: socket.socket) -> bytes:
    """Everything the service sent until it closed the connection."""
    connection.settimeout(10)
    received = bytearray()
    while chunk := connection.recv(1 << 20):
        received += chunk
    return bytes(received)
