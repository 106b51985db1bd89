"""``Cas`` against a hostile gateway on a real socket: whatever it streams, a download ends
within its bounds, and a refused one leaves nothing behind."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from robocloud.car import CARV2_PRAGMA
from robocloud.cas import Cas, CasError
from robocloud.cid import CID

ENDLESS_CAP = 64 << 20
"""Where the endless server stops, so that a client that never would still ends the test."""


@dataclass
class Endless:
    url: str
    sent: int = 0


@contextmanager
def endless_server(head: bytes) -> Iterator[Endless]:
    """A server answering every GET with 200, ``head``, then zeros as fast as they are read
    (until ``ENDLESS_CAP``); ``sent`` counts the zeros."""
    state = Endless("")

    class Flood(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "application/vnd.ipld.car")
            self.send_header("Connection", "close")
            self.end_headers()
            zeros = bytes(1 << 16)
            try:
                self.wfile.write(head)
                while state.sent < ENDLESS_CAP:
                    self.wfile.write(zeros)
                    state.sent += len(zeros)
            except OSError:
                return

        def log_message(self, *args: object) -> None:
            return None

    server = ThreadingHTTPServer(("127.0.0.1", 0), Flood)
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True).start()
    state.url = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        yield state
    finally:
        server.shutdown()
        server.server_close()


def test_a_carv2_whose_payload_never_comes_is_refused_at_its_pragma(tmp_path: Path) -> None:
    """A CARv2 declaring its payload at byte 2^62 had its padding read to the end of the
    stream, --max-size or not: a gateway streaming zeros held `robocloud get` forever."""
    offsets = (1 << 62, 1, 0)
    header = bytes(16) + b"".join(n.to_bytes(8, "little") for n in offsets)
    root = CID.from_block(b"a raw file")
    with (
        endless_server(CARV2_PRAGMA + header) as gateway,
        Cas(gateway.url, retries=0) as cas,
        pytest.raises(CasError, match="a CARv2, where only a CARv1 is read"),
    ):
        cas.get_to_file(root, tmp_path / "out", max_size=1 << 20)
    assert gateway.sent < ENDLESS_CAP // 4
    assert list(tmp_path.iterdir()) == []
