"""Path resolution and the gateway's directory page read within ``WALK_READ_BYTES``.

Both answer a few hundred bytes whatever they read: directories and HAMT shards carrying
megabytes in a UnixFS field no reader knows (number 15, skipped but read and hashed) used to
be read whole at every request, a path on the gateway or ``cat`` with no turn to wait for at
all. In process over ``httpx.ASGITransport`` (``test_listing_routes``), so the test can lower
the budget and count what the store reads.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi import FastAPI

from robocloud.cid import CID, DAG_PB, RAW
from robocloud.dagpb import Link, PBNode, len_field
from robocloud.unixfs import DIRECTORY, HAMT_SHARD, MURMUR3_X64_64, UnixfsData
from services.cas import store as store_module
from services.cas.app import build_app
from services.cas.settings import CasSettings
from services.cas.store import ContentStore
from tests.unit.services.cas.test_listing_routes import ROBOT, call, count_reads, store_of

JUNK = 64 * 1024
BUDGET = 3 * JUNK + 4096
"""Room for three padded blocks and the small ones around them, not for a fourth."""


@pytest.fixture
def app(tmp_path: Path) -> Iterator[FastAPI]:
    built = build_app(CasSettings(data_dir=tmp_path, cas_gc_interval_s=0))
    yield built
    built.state.store.close()


def padded_node(links: list[Link], unixfs: UnixfsData) -> bytes:
    """A dag-pb node whose UnixFS data carries ``JUNK`` bytes in field 15."""
    return PBNode(links, unixfs.encode() + len_field(15, b"\0" * JUNK)).encode()


def put(store: ContentStore, block: bytes, codec: int = DAG_PB) -> CID:
    (cid,) = store.put_blocks([block], codec, ROBOT, pin=False)
    return cid


def bytes_read(store: ContentStore, reads: dict[bytes, int]) -> int:
    return sum(store.blocks.locate(CID(1, RAW, mh)).length * n for mh, n in reads.items())


def test_the_gateway_page_of_a_hamt_of_padded_shards_stops_at_the_read_budget(
    app: FastAPI, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Eight shards of one entry each, 64 KiB of junk apiece: the page of eight names read
    all 512 KiB (a few hundred shards of 8 MiB: gigabytes a request, holding a listing turn
    that long). It now stops at the budget, 400 naming the shard it stopped at."""
    monkeypatch.setattr(store_module, "WALK_READ_BYTES", BUDGET, raising=False)
    store = store_of(app)
    leaf = put(store, b"leaf", RAW)
    shard = UnixfsData(HAMT_SHARD, b"\xff", hash_type=MURMUR3_X64_64, fanout=256)
    shards = [put(store, padded_node([Link(leaf, f"AAentry{i}", 4)], shard)) for i in range(8)]
    root_links = [Link(cid, f"{i:02X}", JUNK) for i, cid in enumerate(shards)]
    root = put(store, PBNode(root_links, shard.encode()).encode())
    reads = count_reads(store, monkeypatch)

    answer = call(app, "GET", f"/ipfs/{root}/", headers={"Accept": "text/html"})

    assert answer.status_code == 400, answer.text[:300]
    error = answer.json()["error"]
    assert error["code"] == "too_much_to_read"
    assert error["details"]["limit_bytes"] == BUDGET
    assert error["details"]["cid"] in {str(cid) for cid in shards}
    assert "field" not in error["details"]
    assert bytes_read(store, reads) <= 2 * BUDGET  # kind and index.html lookup: own budgets
    assert not any(reads[shard.multihash] for shard in shards[4:])


def padded_path(store: ContentStore, depth: int) -> tuple[CID, list[CID], str]:
    """A file under ``depth`` nested directories named ``d``, each padded: the root, the
    directories from the root down, and the path to the file."""
    child = put(store, b"the file", RAW)
    name = "file"
    directories: list[CID] = []
    for _ in range(depth):
        child = put(store, padded_node([Link(child, name, 8)], UnixfsData(DIRECTORY)))
        directories.insert(0, child)
        name = "d"
    return child, directories, "/".join(["d"] * (depth - 1) + ["file"])


@pytest.mark.parametrize("route", ["gateway", "gateway-car", "cat"])
def test_a_path_through_padded_directories_stops_at_the_read_budget(
    app: FastAPI, monkeypatch: pytest.MonkeyPatch, route: str
) -> None:
    """Six directories of 64 KiB junk on the way to an 8-byte file: every one was read and
    hashed before the file was (256 segments of 8 MiB: 2 GiB a GET, on a worker thread that
    no turn limits). The path stops at the budget, 400 naming the directory; ``cat`` names
    its ``arg``."""
    monkeypatch.setattr(store_module, "WALK_READ_BYTES", BUDGET, raising=False)
    store = store_of(app)
    root, directories, path = padded_path(store, 6)
    reads = count_reads(store, monkeypatch)

    if route == "cat":
        answer = call(app, "POST", "/api/v0/cat", params={"arg": f"{root}/{path}"})
    else:
        params = {"format": "car"} if route == "gateway-car" else {}
        answer = call(app, "GET", f"/ipfs/{root}/{path}", params=params)

    assert answer.status_code == 400, answer.text[:300]
    error = answer.json()["error"]
    assert error["code"] == "too_much_to_read"
    assert error["details"]["cid"] == str(directories[3])
    assert error["details"]["limit_bytes"] == BUDGET
    assert error["details"].get("field") == ("arg" if route == "cat" else None)
    assert bytes_read(store, reads) <= BUDGET
    assert not any(reads[directory.multihash] for directory in directories[3:])


def test_a_path_within_the_read_budget_is_answered(
    app: FastAPI, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Three padded directories fit the same budget: the file is served as before."""
    monkeypatch.setattr(store_module, "WALK_READ_BYTES", BUDGET, raising=False)
    store = store_of(app)
    root, _, path = padded_path(store, 3)

    got = call(app, "GET", f"/ipfs/{root}/{path}")
    cat = call(app, "POST", "/api/v0/cat", params={"arg": f"{root}/{path}"})

    assert (got.status_code, got.content) == (200, b"the file")
    assert (cat.status_code, cat.content) == (200, b"the file")
