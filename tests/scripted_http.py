"""A real HTTP server on loopback whose answers a test scripts: flaky, slow, lying or hostile.

The SDK's retries, bounds and error translation are tested against real sockets rather than a
fake transport, so what httpx does with a dropped connection or a stalled answer is what the
test sees. A script gets each request and returns ``(status, headers, body)``, or ``None`` to
close the connection without answering (a crash after the request arrived). Like every
robocloud service, the server answers ``GET /v1/audience`` itself (signed requests name it),
outside the script and the record, unless it is told to leave that to the script too.
"""

from __future__ import annotations

import json
import ssl
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from robocloud.client import ServiceClient


@dataclass(frozen=True)
class Exchange:
    """One request as the server received it."""

    method: str
    path: str
    headers: dict[str, str]
    body: bytes


Reply = tuple[int, dict[str, str], bytes] | None
Script = Callable[[Exchange], Reply]


@dataclass
class ScriptedServer:
    url: str
    exchanges: list[Exchange] = field(default_factory=list)

    def count(self, method: str | None = None) -> int:
        return sum(1 for e in self.exchanges if method is None or e.method == method)


@contextmanager
def scripted_client(
    script: Script, **options: Any
) -> Iterator[tuple[ScriptedServer, ServiceClient]]:
    """A ``ServiceClient`` (built with ``options``) on a server running ``script``."""
    with scripted_server(script) as server, ServiceClient(server.url, **options) as client:
        yield server, client


AUDIENCE = {"audience": "scripted@local", "service": "scripted", "deployment": "local"}


@contextmanager
def scripted_server(script: Script, *, answer_audience: bool = True) -> Iterator[ScriptedServer]:
    """Serve ``script`` on a free loopback port until the block ends."""
    record: list[Exchange] = []

    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def _body(self) -> bytes:
            """The request's body, whole: a reply to a half-read body resets the connection."""
            if self.headers.get("Transfer-Encoding", "").lower() != "chunked":
                length = int(self.headers.get("Content-Length") or 0)
                return self.rfile.read(length) if length else b""
            body = bytearray()
            while size := int(self.rfile.readline().split(b";")[0], 16):
                body += self.rfile.read(size)
                self.rfile.readline()
            while self.rfile.readline() not in (b"\r\n", b"\n", b""):
                continue
            return bytes(body)

        def _handle(self) -> None:
            body = self._body()
            exchange = Exchange(
                self.command, self.path, {k.lower(): v for k, v in self.headers.items()}, body
            )
            if answer_audience and (self.command, self.path) == ("GET", "/v1/audience"):
                reply = json_reply(json.dumps(AUDIENCE))
            else:
                record.append(exchange)
                reply = script(exchange)
            if reply is None:
                self.close_connection = True
                return
            status, headers, content = reply
            self.send_response(status)
            for name, value in headers.items():
                self.send_header(name, value)
            if "Content-Length" not in headers and "Transfer-Encoding" not in headers:
                self.send_header("Content-Length", str(len(content)))
            self.end_headers()
            self.wfile.write(content)

        def do_GET(self) -> None:
            self._handle()

        def do_POST(self) -> None:
            self._handle()

        def do_PUT(self) -> None:
            self._handle()

        def log_message(self, *args: object) -> None:
            return None

    with serving(Handler) as url:
        yield ScriptedServer(url, record)


@contextmanager
def serving(
    handler: type[BaseHTTPRequestHandler], tls: ssl.SSLContext | None = None
) -> Iterator[str]:
    """Serve ``handler`` on a free loopback port, a thread per connection, over ``tls`` when
    given; its base URL."""
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    server.daemon_threads = True
    if tls is not None:
        server.socket = tls.wrap_socket(server.socket, server_side=True)
    threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True).start()
    try:
        yield f"{'https' if tls else 'http'}://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


def json_reply(body: bytes | str, status: int = 200, **headers: str) -> Reply:
    raw = body.encode() if isinstance(body, str) else body
    return status, {"Content-Type": "application/json", **headers}, raw


def nested_json(depth: int) -> bytes:
    """``[[[...]]]``: what a hostile service answers to crash a client's JSON parser."""
    return b"[" * depth + b"]" * depth
