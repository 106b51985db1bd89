"""``Cas`` against a hostile gateway on a real socket: whatever it streams, a download ends
within its bounds, and a refused one leaves nothing behind."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler
from pathlib import Path

import pytest

from robocloud.car import CARV2_PRAGMA, write_car
from robocloud.cas import Cas, CasError, ContentTooLargeError
from robocloud.cid import CID, DAG_PB, RAW
from robocloud.dagpb import Link, PBNode
from robocloud.unixfs import FILE, UnixfsData
from tests.scripted_http import Exchange, Reply, scripted_server, serving

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

    with serving(Flood) as state.url:
        yield state


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


def expanding_file(leaf_size: int, copies: int) -> tuple[CID, bytes, bytes]:
    """A file of ``copies`` times one zero leaf: its root, the root's block and its CAR,
    which holds the leaf once."""
    leaf = bytes(leaf_size)
    leaf_cid = CID.from_block(leaf, RAW)
    data = UnixfsData(FILE, filesize=leaf_size * copies, blocksizes=[leaf_size] * copies)
    links = [Link(leaf_cid, "", leaf_size)] * copies
    node = PBNode(links, data.encode()).encode()
    root = CID.from_block(node, DAG_PB)
    return root, node, b"".join(write_car([root], [(root, node), (leaf_cid, leaf)]))


def test_get_holds_no_more_than_an_answer_by_default() -> None:
    """A 64 KiB CAR of 4 MiB of content: get without max_size held whatever the DAG expanded
    to, so a few kilobytes linked over and over filled the robot's memory."""
    root, node, car = expanding_file(1 << 16, 64)

    def script(exchange: Exchange) -> Reply:
        if "format=raw" in exchange.path:
            return 200, {"Content-Type": "application/vnd.ipld.raw"}, node
        return 200, {"Content-Type": "application/vnd.ipld.car"}, car

    with scripted_server(script) as gateway:
        with (
            Cas(gateway.url, retries=0, max_answer_bytes=1 << 20) as cas,
            pytest.raises(ContentTooLargeError, match=f"limit of {1 << 20} bytes"),
        ):
            cas.get(root)
        with Cas(gateway.url, retries=0) as cas:
            assert cas.get(root) == bytes(4 << 20)


def test_get_to_file_writes_no_more_than_the_free_space_by_default(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without max_size a DAG expanding past the disk's free space was written until the
    disk was full."""
    root, node, car = expanding_file(1 << 16, 64)
    free = shutil.disk_usage(tmp_path)._replace(free=1 << 20)
    monkeypatch.setattr("robocloud.partial.shutil.disk_usage", lambda _: free)

    def script(exchange: Exchange) -> Reply:
        if "format=raw" in exchange.path:
            return 200, {"Content-Type": "application/vnd.ipld.raw"}, node
        return 200, {"Content-Type": "application/vnd.ipld.car"}, car

    with (
        scripted_server(script) as gateway,
        Cas(gateway.url, retries=0) as cas,
        pytest.raises(ContentTooLargeError, match=f"more than the limit of {1 << 20} bytes"),
    ):
        cas.get_to_file(root, tmp_path / "out")
    assert list(tmp_path.iterdir()) == []
