"""Answers read off a bare socket, for requests no client library sends: a head dribbled a
byte at a time, one more download beside a client's stalled ones."""

from __future__ import annotations

import json
import socket
from typing import Any


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
    assert (
        answer.get("error", {}).get("request_id", headers["x-request-id"])
        == (headers["x-request-id"])
    )
    return int(lines[0].split()[1]), answer
