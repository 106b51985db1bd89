"""A robot's view: the SDK and CLI against a real gateway, and against lying ones."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from typer.testing import CliRunner

from robocloud.car import write_car
from robocloud.cas import Cas, CasError
from robocloud.cid import CID
from robocloud.cli import app
from robocloud.identity import Identity
from robocloud.unixfs import Block, ImportParams, import_bytes
from tests.procs import ServiceProcess

runner = CliRunner()


def test_large_file_round_trip_with_repeated_chunks(cas: Cas, tmp_path: Path) -> None:
    data = bytes(5 * 262144) + bytes(range(251)) * 3000 + bytes(262144 * 2)
    source = tmp_path / "in.bin"
    source.write_bytes(data)
    seen: list[int] = []
    cid = cas.add_file(source)
    assert cid == import_bytes(data)[1]
    size = cas.get_to_file(cid, tmp_path / "out.bin", progress=seen.append)
    assert size == len(data) == sum(seen)
    assert (tmp_path / "out.bin").read_bytes() == data
    assert not (tmp_path / ".out.bin.partial").exists()


@pytest.mark.parametrize(
    "params",
    [
        ImportParams(cid_version=0, raw_leaves=False),
        ImportParams(chunk_size=1000),
        ImportParams.from_options(profile="unixfs-v1-2025"),
    ],
    ids=["v0-dag-pb-leaves", "deep-tree", "v1-2025"],
)
def test_every_layout_reads_back(cas: Cas, params: ImportParams) -> None:
    data = bytes(range(251)) * 9000 + bytes(40_000)
    cid = cas.add_bytes(data, params=params)
    assert cid == import_bytes(data, params)[1]
    assert cas.get(cid) == data


def test_pin_unpin_and_pins(cas: Cas, identity: Identity) -> None:
    cid = cas.add_bytes(b"keep me", pin=False)
    assert cas.pins() == {}
    cas.pin(cid)
    assert cas.pins() == {str(cid): {"Type": "recursive", "Owners": [identity.address]}}
    cas.unpin(cid)
    assert cas.pins() == {}


def gateway_answering(answer: Callable[[str], tuple[int, str, bytes]]) -> Iterator[str]:
    class Gateway(BaseHTTPRequestHandler):
        def _reply(self) -> None:
            status, content_type, body = answer(self.path)
            self.send_response(status)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self) -> None:
            self._reply()

        def do_POST(self) -> None:
            self._reply()

        def log_message(self, *args: object) -> None:
            return None

    server = ThreadingHTTPServer(("127.0.0.1", 0), Gateway)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


DATA = bytes(range(251)) * 3000
BLOCKS, ROOT = import_bytes(DATA)
CAR = "application/vnd.ipld.car"


def car_of(blocks: list[Block], root: CID = ROOT) -> bytes:
    return b"".join(write_car([root], blocks))


@pytest.mark.parametrize(
    ("car", "message"),
    [
        (car_of([*BLOCKS[:-1], BLOCKS[-1]]), "is due"),  # the root last
        (car_of([BLOCKS[-1], BLOCKS[1], BLOCKS[0], *BLOCKS[2:-1]]), "is due"),
        (car_of([BLOCKS[-1], BLOCKS[0]]), "ends before block"),
        (car_of([BLOCKS[-1], *BLOCKS[:-1], Block(CID.from_block(b"x"), b"x")]), "beyond"),
        (car_of(BLOCKS[:1], BLOCKS[0].cid), "rooted at"),
        (car_of([BLOCKS[-1], Block(BLOCKS[0].cid, b"forged"), *BLOCKS[1:-1]]), "does not match"),
    ],
    ids=["order", "swapped", "short", "extra", "other-root", "forged"],
)
def test_get_refuses_what_a_lying_gateway_sends(car: bytes, message: str, tmp_path: Path) -> None:
    for url in gateway_answering(lambda _: (200, CAR, car)):
        with Cas(url, retries=0) as client, pytest.raises(CasError, match=message):
            client.get_to_file(ROOT, tmp_path / "out.bin")
    assert list(tmp_path.iterdir()) == []


def test_add_refuses_a_wrong_answer(tmp_path: Path) -> None:
    lie = b'{"Name":"f","Hash":"bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"}\n'
    audience = b'{"audience":"cas@local","service":"cas","deployment":"local"}'

    def answer(path: str) -> tuple[int, str, bytes]:
        return 200, "application/json", audience if path == "/v1/audience" else lie

    for url in gateway_answering(answer):
        client = Cas(url, Identity.generate(), retries=0)
        with client, pytest.raises(CasError, match="but the file's CID is"):
            client.add_bytes(b"not hello world")


def test_cli_put_get_pin_pins(
    cas_service: ServiceProcess, identity: Identity, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    keystore = tmp_path / "key.json"
    identity.save(keystore, "pw", scrypt_n=2**4)
    monkeypatch.setenv("ROBOCLOUD_PASSPHRASE", "pw")
    source = tmp_path / "notes.txt"
    source.write_bytes(b"Hello world")
    common = ["--cas", cas_service.url]
    put = runner.invoke(app, ["put", str(source), "--keystore", str(keystore), *common])
    assert put.exit_code == 0, put.output
    cid = put.output.strip()
    assert cid == "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"
    got = runner.invoke(app, ["get", cid, "-o", str(tmp_path / "back.txt"), *common])
    assert got.exit_code == 0, got.output
    assert "verified" in got.output
    assert (tmp_path / "back.txt").read_bytes() == b"Hello world"
    listed = runner.invoke(app, ["pins", *common])
    assert listed.output.split() == [cid, identity.address]
    unpinned = runner.invoke(app, ["unpin", cid, "--keystore", str(keystore), *common])
    assert unpinned.exit_code == 0, unpinned.output
    missing = runner.invoke(
        app,
        [
            "get",
            "bafkreibercdsoj77g6v724b2gdmwwblgejcogoat4eatckoanjo2periym",
            "-o",
            str(tmp_path / "x"),
            *common,
        ],
    )
    assert missing.exit_code == 1
    assert "block_not_found" in missing.output or "not in this store" in missing.output
