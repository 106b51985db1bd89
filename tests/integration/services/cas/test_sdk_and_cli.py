"""A robot's view: the SDK and CLI against a real gateway, and against lying ones."""

from __future__ import annotations

import base64
import json
import os
import pty
import subprocess
import sys
from collections.abc import Callable, Iterator
from http.server import BaseHTTPRequestHandler
from pathlib import Path

import pytest
from typer.testing import CliRunner

import robocloud
from robocloud.car import write_car
from robocloud.cas import Cas, CasError, ContentTooLargeError
from robocloud.cid import CID, DAG_PB, Block
from robocloud.cid import RAW as RAW_CODEC
from robocloud.cli import app
from robocloud.dagpb import Link, PBNode
from robocloud.errors import BadRequestError
from robocloud.identity import Identity
from robocloud.unixfs import FILE, ImportParams, UnixfsData, import_bytes
from tests.conftest import ServiceFactory
from tests.integration.services.cas.conftest import QUIET_GC
from tests.procs import ServiceProcess, free_port
from tests.scripted_http import nested_json, serving

runner = CliRunner()


@pytest.fixture(scope="module")
def cas_service(shared_cas_service: ServiceProcess) -> ServiceProcess:
    return shared_cas_service


@pytest.fixture
def own_cas_service(service_factory: ServiceFactory) -> ServiceProcess:
    """A cas for this test alone: for tests that list every pin of the store."""
    return service_factory("cas", QUIET_GC)


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
    assert list(tmp_path.glob(".out.bin*")) == []


LAYOUTS = pytest.mark.parametrize(
    "params",
    [
        ImportParams(cid_version=0, raw_leaves=False),
        ImportParams(chunk_size=1000),
        ImportParams.from_options(profile="unixfs-v1-2025"),
    ],
    ids=["v0-dag-pb-leaves", "deep-tree", "v1-2025"],
)
LAYOUT_DATA = bytes(range(251)) * 9000 + bytes(40_000)


@LAYOUTS
def test_every_layout_reads_back(cas: Cas, params: ImportParams) -> None:
    cid = cas.add_bytes(LAYOUT_DATA, params=params)
    assert cid == import_bytes(LAYOUT_DATA, params)[1]
    assert cas.get(cid) == LAYOUT_DATA


@LAYOUTS
def test_cat_reads_any_range_of_every_layout(cas: Cas, params: ImportParams) -> None:
    """Ranges on chunk edges (1,000, 262,144, 1 MiB), across them, to the end and past it."""
    size = len(LAYOUT_DATA)
    cid = cas.add_bytes(LAYOUT_DATA, params=params)
    ranges = [
        (0, 1),
        (999, 2),
        (262_143, 2),
        (1_048_575, 3),
        (300_000, 1_000_000),
        (0, None),
        (size - 1, None),
        (size - 1, 10),
        (5, 0),
        (size, None),
        (size + 10, 5),
    ]
    for offset, length in ranges:
        end = None if length is None else offset + length
        assert cas.cat(cid, offset, length) == LAYOUT_DATA[offset:end], (offset, length)


def test_cat_of_a_raw_block_and_an_empty_file(cas: Cas) -> None:
    small = cas.add_bytes(b"a small file", params=ImportParams(cid_version=1))
    assert small.codec == RAW_CODEC
    assert cas.cat(small, 2, 5) == b"small"
    assert cas.cat(small, 12) == b""
    empty = cas.add_bytes(b"")
    assert cas.cat(empty) == b""
    assert cas.cat(empty, 3, 2) == b""


def test_cat_refuses_a_range_over_the_answer_limit(cas: Cas, cas_service: ServiceProcess) -> None:
    cid = cas.add_bytes(LAYOUT_DATA)
    with Cas(cas_service.url, retries=0, max_answer_bytes=100_000) as limited:
        assert limited.cat(cid, 10, 100_000) == LAYOUT_DATA[10:100_010]
        with pytest.raises(ContentTooLargeError, match="more than the limit of 100000 bytes"):
            limited.cat(cid, 10, 100_001)
        with pytest.raises(ContentTooLargeError, match="more than the limit of 100000 bytes"):
            limited.cat(cid, 10)
    with pytest.raises(ValueError, match="offset -1"):
        cas.cat(cid, -1)


def test_pin_unpin_and_pins(own_cas_service: ServiceProcess, identity: Identity) -> None:
    with Cas(own_cas_service.url, identity, retries=0) as cas:
        cid = cas.add_bytes(b"keep me", pin=False)
        assert cas.pins() == {}
        cas.pin(cid)
        assert cas.pins() == {str(cid): {"Type": "recursive", "Owners": [identity.address]}}
        cas.unpin(cid)
        assert cas.pins() == {}


def gateway_answering(answer: Callable[[str], tuple[int, str, bytes]]) -> Iterator[str]:
    class Gateway(BaseHTTPRequestHandler):
        def _reply(self) -> None:
            # Read what the client sends, as any server does before answering: the SDK
            # computes its CIDs from the body it streams.
            self.rfile.read(int(self.headers.get("Content-Length") or 0))
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

    with serving(Gateway) as url:
        yield url


DATA = bytes(range(251)) * 3000
BLOCKS, ROOT = import_bytes(DATA)
CAR = "application/vnd.ipld.car"
RAW = "application/vnd.ipld.raw"


def car_of(blocks: list[Block], root: CID = ROOT) -> bytes:
    return b"".join(write_car([root], blocks))


@pytest.mark.parametrize(
    ("car", "message"),
    [
        (car_of([*BLOCKS[:-1], BLOCKS[-1]]), "is due"),  # the root last
        (car_of([BLOCKS[-1], BLOCKS[1], BLOCKS[0], *BLOCKS[2:-1]]), "is due"),
        (car_of([BLOCKS[-1], BLOCKS[0]]), "end before block"),
        (car_of([BLOCKS[-1], *BLOCKS[:-1], Block(CID.from_block(b"x"), b"x")]), "beyond"),
        (car_of(BLOCKS[:1], BLOCKS[0].cid), "rooted at"),
        (car_of([BLOCKS[-1], Block(BLOCKS[0].cid, b"forged"), *BLOCKS[1:-1]]), "does not match"),
    ],
    ids=["order", "swapped", "short", "extra", "other-root", "forged"],
)
def test_get_refuses_what_a_lying_gateway_sends(car: bytes, message: str, tmp_path: Path) -> None:
    """The root block comes honest (its declared size is read first), the file's CAR not."""
    (root_block,) = [block.data for block in BLOCKS if block.cid == ROOT]

    def lying(path: str) -> tuple[int, str, bytes]:
        return (200, RAW, root_block) if "format=raw" in path else (200, CAR, car)

    for url in gateway_answering(lying):
        with Cas(url, retries=0) as client, pytest.raises(CasError, match=message):
            client.get_to_file(ROOT, tmp_path / "out.bin")
    assert list(tmp_path.iterdir()) == []


RANGE_CAR = [BLOCKS[-1], BLOCKS[0], BLOCKS[1]]
"""The blocks of bytes 262,140 to 262,149 of ``DATA``: the root and the two leaves they span."""


@pytest.mark.parametrize(
    ("car", "message"),
    [
        (car_of([BLOCKS[-1], Block(BLOCKS[0].cid, b"forged"), BLOCKS[1]]), "does not match"),
        (car_of([BLOCKS[-1], BLOCKS[1]]), "is due"),
        (car_of(RANGE_CAR[:2]), "end before block"),
        (car_of([*RANGE_CAR, BLOCKS[2]]), "beyond the range"),
        (car_of(RANGE_CAR, BLOCKS[0].cid), "rooted at"),
    ],
    ids=["forged", "skipped", "short", "extra", "other-root"],
)
def test_cat_refuses_what_a_lying_gateway_sends(car: bytes, message: str) -> None:
    paths: list[str] = []

    def lying(path: str) -> tuple[int, str, bytes]:
        paths.append(path)
        return 200, CAR, car

    for url in gateway_answering(lying):
        with Cas(url, retries=0) as client, pytest.raises(CasError, match=message):
            client.cat(ROOT, 262_140, 10)
    assert "entity-bytes=262140%3A262149" in paths[0]


def test_cat_believes_no_claim_that_a_range_is_past_the_end() -> None:
    """A gateway may say the range lies outside the file; the verified root says otherwise."""
    (root_block,) = [block.data for block in BLOCKS if block.cid == ROOT]
    refusal = json.dumps(
        {"error": {"code": "invalid_entity_bytes", "message": "outside the file of 3 bytes"}}
    ).encode()

    def lying(path: str) -> tuple[int, str, bytes]:
        if "format=raw" in path:
            return 200, RAW, root_block
        return 400, "application/json", refusal

    for url in gateway_answering(lying):
        with Cas(url, retries=0) as client:
            with pytest.raises(BadRequestError, match="invalid_entity_bytes"):
                client.cat(ROOT, 10, 5)
            assert client.cat(ROOT, len(DATA)) == b""


OTHER_CID = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"


@pytest.mark.parametrize(
    ("lie", "message"),
    [
        (f'{{"Name":"0","Hash":"{OTHER_CID}"}}\n', "but the file's CID is"),
        (f'{{"Name":"f","Hash":"{OTHER_CID}"}}\n', "names no file 0"),
    ],
    ids=["other-cid", "other-name"],
)
def test_add_refuses_a_wrong_answer(lie: str, message: str) -> None:
    """Bytes go up as files named by their place (``add_blobs``), each named in the answer."""
    audience = b'{"audience":"cas@local","service":"cas","deployment":"local"}'

    def answer(path: str) -> tuple[int, str, bytes]:
        return 200, "application/json", audience if path == "/v1/audience" else lie.encode()

    for url in gateway_answering(answer):
        client = Cas(url, Identity.generate(), retries=0)
        with client, pytest.raises(CasError, match=message):
            client.add_bytes(b"not hello world")


def test_many_blobs_go_up_in_one_add_each_pinned(cas: Cas) -> None:
    blobs = [b"first", b"", b"first", bytes(range(256)) * 2000]
    cids = cas.add_blobs(blobs)
    assert cids == [import_bytes(blob)[1] for blob in blobs]
    assert cids[0] == cids[2]
    assert [cas.get(cid) for cid in cids] == blobs
    assert {str(cid) for cid in cids} <= cas.pins().keys()
    assert cas.add_blobs([]) == []


def test_add_directory_refuses_a_wrong_root(tmp_path: Path) -> None:
    root = tmp_path / "dir"
    root.mkdir()
    (root / "f").write_bytes(b"Hello world")
    lie = (
        b'{"Name":"dir/f","Hash":"bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"}\n'
        b'{"Name":"dir","Hash":"bafybeiczsscdsbs7ffqz55asqdf3smv6klcw3gofszvwlyarci47bgf354"}\n'
    )
    audience = b'{"audience":"cas@local","service":"cas","deployment":"local"}'

    def answer(path: str) -> tuple[int, str, bytes]:
        return 200, "application/json", audience if path == "/v1/audience" else lie

    for url in gateway_answering(answer):
        client = Cas(url, Identity.generate(), retries=0)
        with client, pytest.raises(CasError, match="but the directory's CID is"):
            client.add_directory(root)


@pytest.fixture
def work(tmp_path: Path) -> Path:
    """A directory of this test's files alone (the service keeps its data in ``tmp_path``)."""
    path = tmp_path / "work"
    path.mkdir()
    return path


def test_cli_put_get_pin_pins(
    own_cas_service: ServiceProcess, identity: Identity, keystore: Path, tmp_path: Path
) -> None:
    source = tmp_path / "notes.txt"
    source.write_bytes(b"Hello world")
    common = ["--cas", own_cas_service.url]
    put = runner.invoke(app, ["put", str(source), "--keystore", str(keystore), *common])
    assert put.exit_code == 0, put.output
    cid = put.stdout.strip()
    assert cid == "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"
    got = runner.invoke(app, ["get", cid, "-o", str(tmp_path / "back.txt"), *common])
    assert got.exit_code == 0, got.output
    assert got.stdout == f"{cid} -> {tmp_path / 'back.txt'} (11 bytes, verified)\n"
    assert len(got.stdout) > 100  # one line, wider than the 80 columns rich assumes off a tty
    assert (tmp_path / "back.txt").read_bytes() == b"Hello world"
    listed = runner.invoke(app, ["pins", *common])
    assert listed.stdout.split() == [cid, identity.address]
    share = runner.invoke(app, ["pinned", "--keystore", str(keystore), *common])
    bound = "at most 16.0 GiB (17179869184 bytes)"
    assert share.stdout == (
        f"{identity.address} keeps 11 bytes pinned ({bound}) and wrote 11 bytes in the last "
        f"hour ({bound})\n"
    )
    unpinned = runner.invoke(app, ["unpin", cid, "--keystore", str(keystore), *common])
    assert unpinned.exit_code == 0, unpinned.output
    assert runner.invoke(app, ["pins", *common]).stdout == ""
    share = runner.invoke(app, ["pinned", "--keystore", str(keystore), *common])
    assert share.stdout.startswith(f"{identity.address} keeps 0 bytes pinned ({bound}) and")
    absent = "bafkreibercdsoj77g6v724b2gdmwwblgejcogoat4eatckoanjo2periym"
    missing = runner.invoke(app, ["get", absent, "-o", str(tmp_path / "x"), *common])
    assert missing.exit_code == 4
    assert missing.stderr.startswith("error: 404 ")
    assert missing.stderr.count("\n") == 1
    assert not (tmp_path / "x").exists()


def test_cli_cat_prints_a_verified_range(cas: Cas, cas_service: ServiceProcess) -> None:
    cid = cas.add_bytes(LAYOUT_DATA)

    def cat(*args: str) -> subprocess.CompletedProcess[bytes]:
        command = [str(Path(sys.executable).with_name("robocloud")), "cat", str(cid), *args]
        return subprocess.run(
            [*command, "--cas", cas_service.url], capture_output=True, timeout=120, check=False
        )

    ranged = cat("--offset", "262000", "--length", "5000")
    assert (ranged.returncode, ranged.stdout) == (0, LAYOUT_DATA[262_000:267_000]), ranged.stderr
    assert cat().stdout == LAYOUT_DATA
    described = json.loads(cat("--offset", "3", "--length", "4", "--json").stdout)
    content = base64.b64encode(LAYOUT_DATA[3:7]).decode()
    assert described == {
        "cid": str(cid),
        "offset": 3,
        "size": 4,
        "verified": True,
        "content_base64": content,
    }
    past = cat("--offset", str(len(LAYOUT_DATA) + 1))
    assert (past.returncode, past.stdout, past.stderr) == (0, b"", b"")
    too_long = cat("--length", str((64 << 20) + 1))
    assert (too_long.returncode, too_long.stdout) == (1, b"")
    assert too_long.stderr.startswith(f"error: {cid} holds more than the limit of".encode())
    assert b"print a smaller --length, or use get -o FILE" in too_long.stderr
    negative = cat("--offset", "-1")
    assert (negative.returncode, negative.stdout) == (2, b"")
    assert b"--offset" in negative.stderr


def test_cli_prints_json_on_request(
    own_cas_service: ServiceProcess, identity: Identity, keystore: Path, tmp_path: Path
) -> None:
    source = tmp_path / "notes.txt"
    source.write_bytes(b"Hello world")
    common = ["--cas", own_cas_service.url, "--json"]
    signed = [*common, "--keystore", str(keystore)]
    put = runner.invoke(app, ["put", str(source), "--no-pin", *signed])
    cid = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"
    assert json.loads(put.stdout) == {"cid": cid, "size": 11, "pinned": False}
    assert json.loads(runner.invoke(app, ["pins", *common]).stdout) == {"pins": []}
    pinned = runner.invoke(app, ["pin", cid, *signed])
    assert json.loads(pinned.stdout) == {"cid": cid, "pinned": True}
    assert json.loads(runner.invoke(app, ["pins", *common]).stdout) == {
        "pins": [{"cid": cid, "type": "recursive", "owners": [identity.address]}]
    }
    assert json.loads(runner.invoke(app, ["pinned", *signed]).stdout) == {
        "robot": identity.address,
        "pinned_bytes": 11,
        "max_bytes": 16 * 1024**3,
        "written_bytes_last_hour": 11,
        "max_written_bytes_per_hour": 16 * 1024**3,
    }
    out = tmp_path / "out.txt"
    got = runner.invoke(app, ["get", cid, "-o", str(out), *common])
    assert json.loads(got.stdout) == {"cid": cid, "path": str(out), "size": 11, "verified": True}
    unpinned = runner.invoke(app, ["unpin", cid, *signed])
    assert json.loads(unpinned.stdout) == {"cid": cid, "pinned": False}


def test_get_refuses_to_overwrite_without_force(
    cas: Cas, cas_service: ServiceProcess, work: Path
) -> None:
    cid = str(cas.add_bytes(b"fresh content"))
    out = work / "out.txt"
    out.write_bytes(b"precious")
    common = [cid, "-o", str(out), "--cas", cas_service.url]
    refused = runner.invoke(app, ["get", *common])
    assert refused.exit_code == 1
    assert refused.stderr == f"error: {out} exists (hint: pass --force to replace it)\n"
    assert out.read_bytes() == b"precious"
    assert sorted(path.name for path in work.iterdir()) == ["out.txt"]
    replaced = runner.invoke(app, ["get", *common, "--force"])
    assert replaced.exit_code == 0, replaced.output
    assert out.read_bytes() == b"fresh content"


def test_the_sdk_never_replaces_a_file_that_appeared_during_the_download(
    cas: Cas, work: Path
) -> None:
    cid = cas.add_bytes(b"x" * 1000)
    out = work / "out.bin"

    def someone_else_writes(_: int) -> None:
        out.write_bytes(b"theirs")

    with pytest.raises(FileExistsError):
        cas.get_to_file(cid, out, someone_else_writes, overwrite=False)
    assert out.read_bytes() == b"theirs"
    assert sorted(path.name for path in work.iterdir()) == ["out.bin"]


def test_a_file_larger_than_max_size_is_refused_before_anything_is_written(
    cas: Cas, work: Path
) -> None:
    data = bytes(range(256)) * 4096
    cid = cas.add_bytes(data)
    with pytest.raises(ContentTooLargeError) as refused:
        cas.get_to_file(cid, work / "out.bin", max_size=len(data) - 1)
    assert (refused.value.declared, refused.value.limit) == (len(data), len(data) - 1)
    assert list(work.iterdir()) == []
    assert cas.get_to_file(cid, work / "out.bin", max_size=len(data)) == len(data)
    assert cas.get(cid, max_size=len(data)) == data


def robocloud_cli(
    *args: str, stderr: int | None = None, **env: str
) -> subprocess.CompletedProcess[str]:
    """The installed ``robocloud`` command in its own process, as a user or a script runs it."""
    return subprocess.run(
        [str(Path(sys.executable).with_name("robocloud")), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE if stderr is None else stderr,
        text=True,
        env={**os.environ, "COLUMNS": "80", **env},
        timeout=120,
    )


def test_put_prints_only_the_cid_while_the_progress_bar_draws_on_a_terminal(
    cas_service: ServiceProcess, keystore: Path, tmp_path: Path
) -> None:
    """``CID=$(robocloud put big.bin)``: stdout is the CID even when stderr shows progress."""
    source = tmp_path / "big.bin"
    data = bytes(range(256)) * (40 * 1024 + 7)
    source.write_bytes(data)
    terminal, terminal_end = pty.openpty()
    try:
        done = robocloud_cli(
            "put",
            str(source),
            "--keystore",
            str(keystore),
            "--cas",
            cas_service.url,
            stderr=terminal_end,
            TERM="xterm",
            ROBOCLOUD_PASSPHRASE="pw",
        )
        os.close(terminal_end)
        drawn = read_all(terminal)
    finally:
        os.close(terminal)
    assert done.returncode == 0, drawn
    assert done.stdout == f"{import_bytes(data)[1]}\n"
    assert b"put" in drawn
    assert b"/10.5 MB" in drawn


def read_all(fd: int) -> bytes:
    chunks = []
    while True:
        try:
            chunk = os.read(fd, 65536)
        except OSError:
            break
        if not chunk:
            break
        chunks.append(chunk)
    return b"".join(chunks)


def expanding_dag(levels: int, fanout: int, declared: int | None) -> tuple[list[Block], CID]:
    """A file DAG of ``fanout ** levels`` copies of one 1 MiB leaf, in CAR (DFS) order.

    A few kilobytes of blocks expand to ``fanout ** levels`` MiB; ``declared`` makes the root
    lie about its size (None: it tells the truth), consistently: its blocksizes add up to it.
    """
    leaf = Block(CID.from_block(bytes(1 << 20)), bytes(1 << 20))
    child, child_size = leaf.cid, 1 << 20
    nodes: list[Block] = []
    for level in range(levels):
        size = child_size * fanout
        top = level == levels - 1
        lies = top and declared is not None
        filesize = declared if lies and declared is not None else size
        sizes = [filesize // fanout] * fanout if lies else [child_size] * fanout
        unixfs = UnixfsData(FILE, b"", filesize, sizes)
        encoded = PBNode([Link(child, "", child_size)] * fanout, unixfs.encode()).encode()
        nodes.append(Block(CID.from_block(encoded, DAG_PB), encoded))
        child, child_size = nodes[-1].cid, size
    return [*reversed(nodes), leaf], nodes[-1].cid


def serving_dag(blocks: list[Block], root: CID) -> Callable[[str], tuple[int, str, bytes]]:
    """A gateway that answers the root block raw and the DAG as a CAR."""

    def answer(path: str) -> tuple[int, str, bytes]:
        if "format=raw" in path:
            return 200, "application/vnd.ipld.raw", blocks[0].data
        return 200, CAR, car_of(blocks, root)

    return answer


def test_get_refuses_a_dag_declaring_more_than_the_free_disk_space(tmp_path: Path) -> None:
    """10**12 MiB declared honestly: refused from the root block alone, no CAR fetched."""
    blocks, root = expanding_dag(levels=4, fanout=1000, declared=None)
    requests: list[str] = []

    def answer(path: str) -> tuple[int, str, bytes]:
        requests.append(path)
        return serving_dag(blocks, root)(path)

    out = tmp_path / "dest" / "out.bin"
    out.parent.mkdir()
    for url in gateway_answering(answer):
        done = robocloud_cli("get", str(root), "-o", str(out), "--cas", url)
    assert done.returncode == 1, done.stderr
    assert done.stdout == ""
    assert done.stderr.startswith(f"error: {root} declares {(1000**4) << 20} bytes, more than")
    assert f"(hint: the limit is the free space in {out.parent}" in done.stderr
    assert done.stderr.count("\n") == 1
    assert list(out.parent.iterdir()) == []
    assert [path.split("?")[1] for path in requests] == ["format=raw"]


def test_get_refuses_a_dag_that_holds_more_than_its_root_declares(tmp_path: Path) -> None:
    """The root says 1,000 bytes; its first child alone holds 10**6 MiB: refused right there."""
    blocks, root = expanding_dag(levels=3, fanout=1000, declared=1000)
    out = tmp_path / "out.bin"
    for url in gateway_answering(serving_dag(blocks, root)):
        done = robocloud_cli("get", str(root), "-o", str(out), "--max-size", "5MiB", "--cas", url)
    assert done.returncode == 6, done.stderr
    assert done.stderr.startswith(f"error: refused the gateway's CAR for {root}")
    assert f"holds {1000**2 << 20} bytes but its parent in {root} declares 1" in done.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("args", "needs_key"),
    [(["pins"], False), (["put", "FILE"], True)],
    ids=["pins", "put"],
)
def test_a_service_answering_deeply_nested_json_is_refused_in_one_line(
    args: list[str], needs_key: bool, keystore: Path, tmp_path: Path
) -> None:
    """100,000 nested brackets: the CLI reports a bad answer instead of segfaulting."""
    source = tmp_path / "file.txt"
    source.write_bytes(b"some bytes")
    args = [str(source) if arg == "FILE" else arg for arg in args]
    key = ["--keystore", str(keystore)] if needs_key else []
    for url in gateway_answering(lambda _: (200, "application/json", nested_json(100_000))):
        done = robocloud_cli(*args, *key, "--cas", url, ROBOCLOUD_PASSPHRASE="pw")
    assert done.returncode == 6, done.stderr
    assert done.stdout == ""
    assert done.stderr.startswith("error: ")
    assert "nested deeper than 64 levels" in done.stderr
    assert done.stderr.count("\n") == 1


def test_an_unreachable_cas_names_its_url_and_setting() -> None:
    url = f"http://127.0.0.1:{free_port()}"
    done = robocloud_cli("pins", ROBOCLOUD_CAS_URL=url)
    assert done.returncode == 3
    assert done.stderr.startswith(f"error: cannot connect to the cas service at {url}")
    assert "ROBOCLOUD_CAS_URL or --cas" in done.stderr
    assert done.stderr.count("\n") == 1


def test_status_and_whoami_report_each_service(
    cas_service: ServiceProcess, identity: Identity, keystore: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Only cas is up: both commands say so per service and exit 3 (one is unreachable)."""
    down = f"http://127.0.0.1:{free_port()}"
    for name in ("ledger", "storage", "broker", "fl"):
        monkeypatch.setenv(f"ROBOCLOUD_{name.upper()}_URL", down)
    monkeypatch.setenv("ROBOCLOUD_CAS_URL", cas_service.url)
    status = runner.invoke(app, ["status", "--json"])
    assert status.exit_code == 3
    report = json.loads(status.stdout)
    cas_row = report["services"][0]
    assert (cas_row["service"], cas_row["health"], cas_row["ready"]) == ("cas", "ok", "ready")
    assert cas_row["version"] == robocloud.__version__
    assert [row["health"] for row in report["services"][1:]] == ["down"] * 4
    assert report["ok"] is False

    whoami = runner.invoke(app, ["whoami", "--json", "--keystore", str(keystore)])
    assert whoami.exit_code == 3
    answer = json.loads(whoami.stdout)
    assert answer["robot"] == identity.address
    assert answer["services"][0] == {"service": "cas", "address": identity.address, "error": None}
    assert all(row["error"].startswith("cannot connect") for row in answer["services"][1:])
