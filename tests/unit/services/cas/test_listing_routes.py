"""``ls`` and the gateway's listings and dag-json, in process over ``httpx.ASGITransport``.

In process, the test can count what the store reads and hold the listing turns itself, which
a service in its own process does not show.
"""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi import FastAPI

from robocloud.cid import CID, DAG_PB, RAW
from robocloud.dagpb import Link, PBNode
from robocloud.directory import directory_node
from robocloud.unixfs import FILE, UnixfsData
from services.cas import kubo
from services.cas import store as store_module
from services.cas.app import build_app
from services.cas.settings import CasSettings
from services.cas.store import ContentStore
from services.common.slots import Slots

ROBOT = "0x" + "ab" * 20
ENTRIES = 300


@pytest.fixture
def app(tmp_path: Path) -> Iterator[FastAPI]:
    built = build_app(CasSettings(data_dir=tmp_path, cas_gc_interval_s=0))
    yield built
    built.state.store.close()


def store_of(app: FastAPI) -> ContentStore:
    store: ContentStore = app.state.store
    return store


def call(app: FastAPI, method: str, path: str, **kwargs: Any) -> httpx.Response:
    async def go() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://cas") as client:
            return await client.request(method, path, **kwargs)

    return asyncio.run(go())


def count_reads(store: ContentStore, monkeypatch: pytest.MonkeyPatch) -> Counter[bytes]:
    """Every block the store reads from its packs, by multihash."""
    reads: Counter[bytes] = Counter()
    get = store.blocks.get

    def counted(cid: CID) -> bytes:
        reads[cid.multihash] += 1
        return get(cid)

    monkeypatch.setattr(store.blocks, "get", counted)
    return reads


def put_directory(store: ContentStore, links: list[Link]) -> CID:
    blocks, link = directory_node(links)
    for block in blocks:
        store.put_blocks([block.data], DAG_PB, ROBOT, pin=False)
    return link.cid


def test_ls_reads_an_entry_repeated_under_many_names_once(
    app: FastAPI, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every entry used to read and re-hash its whole block (65,536 links to one 8 MiB block:
    minutes an ``arg``). A dag-pb entry's block is now read once a request, however many
    names link it; a raw entry's size comes from the index, its block never read."""
    store = store_of(app)
    payload = b"x" * 100_000
    (raw,) = store.put_blocks([payload], RAW, ROBOT, pin=False)
    leaf = PBNode([], UnixfsData(FILE, payload, filesize=len(payload)).encode()).encode()
    (node,) = store.put_blocks([leaf], DAG_PB, ROBOT, pin=False)
    links = [Link(raw, f"raw-{i}", len(payload)) for i in range(ENTRIES)]
    links += [Link(node, f"node-{i}", len(leaf)) for i in range(ENTRIES)]
    directory = put_directory(store, links)
    reads = count_reads(store, monkeypatch)

    answer = call(app, "POST", "/api/v0/ls", params=[("arg", str(directory))] * 2)

    assert answer.status_code == 200, answer.text
    objects = answer.json()["Objects"]
    assert len(objects) == 2
    for listed in objects:
        assert len(listed["Links"]) == 2 * ENTRIES
        assert {(link["Size"], link["Type"]) for link in listed["Links"]} == {(len(payload), 2)}
    assert reads[node.multihash] == 1
    assert reads[raw.multihash] == 0


def test_ls_stops_at_its_read_budget_naming_the_block(
    app: FastAPI, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = store_of(app)
    leaves = [
        PBNode([], UnixfsData(FILE, bytes([i]) * 1000, filesize=1000).encode()).encode()
        for i in range(10)
    ]
    nodes = store.put_blocks(leaves, DAG_PB, ROBOT, pin=False)
    directory = put_directory(store, [Link(c, f"f{i}", 1000) for i, c in enumerate(nodes)])
    monkeypatch.setattr(kubo, "LS_READ_BYTES", store.block_size(directory) + 3_500)

    answer = call(app, "POST", "/api/v0/ls", params={"arg": str(directory)})

    assert answer.status_code == 400, answer.text
    error = answer.json()["error"]
    assert error["code"] == "too_much_to_read"
    assert error["details"]["field"] == "arg"
    assert error["details"]["cid"] in {str(cid) for cid in nodes}


def test_ls_of_more_arguments_than_its_limit_is_refused_naming_arg(
    app: FastAPI, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = store_of(app)
    directory = put_directory(store, [])
    reads = count_reads(store, monkeypatch)

    answer = call(
        app, "POST", "/api/v0/ls", params=[("arg", str(directory))] * (kubo.MAX_LS_ARGS + 1)
    )

    assert answer.status_code == 400, answer.text
    error = answer.json()["error"]
    assert error["code"] == "too_many_arguments"
    assert error["details"] == {"field": "arg", "limit": kubo.MAX_LS_ARGS}
    assert not reads


def test_dag_json_of_a_directory_is_its_node_on_get_and_head(app: FastAPI) -> None:
    store = store_of(app)
    (one, two) = store.put_blocks([b"one", b"two!"], RAW, ROBOT, pin=False)
    directory = put_directory(store, [Link(two, "b", 4), Link(one, "a", 3)])

    got = call(app, "GET", f"/ipfs/{directory}", params={"format": "dag-json"})
    head = call(app, "HEAD", f"/ipfs/{directory}", params={"format": "dag-json"})

    assert got.status_code == 200, got.text
    assert got.headers["content-type"] == "application/vnd.ipld.dag-json"
    assert got.json() == {
        "Data": {"/": {"bytes": "CAE"}},  # UnixFS Data, type Directory
        "Links": [
            {"Hash": {"/": str(one)}, "Name": "a", "Tsize": 3},
            {"Hash": {"/": str(two)}, "Name": "b", "Tsize": 4},
        ],
    }
    assert head.status_code == 200
    assert head.content == b""
    assert head.headers["content-length"] == str(len(got.content))


LISTINGS: dict[str, tuple[str, str, dict[str, Any]]] = {
    "gateway-html": ("GET", "/ipfs/{cid}/", {"headers": {"Accept": "text/html"}}),
    "kubo-ls": ("POST", "/api/v0/ls", {"params": {"arg": "{cid}"}}),
    "dag-json": ("GET", "/ipfs/{cid}", {"params": {"format": "dag-json"}}),
    "dag-json-head": ("HEAD", "/ipfs/{cid}", {"params": {"format": "dag-json"}}),
}


@pytest.mark.parametrize("listing", LISTINGS)
def test_listings_and_dag_json_wait_for_a_listing_turn_then_are_busy(
    app: FastAPI, listing: str
) -> None:
    """A node as dag-json was decoded and encoded on the event loop (0.8 s for 65,536 links,
    20 requests held every route 12.5 s): it now takes the listing turns, and is refused
    like a listing when none comes free."""
    store = store_of(app)
    (leaf,) = store.put_blocks([b"leaf"], RAW, ROBOT, pin=False)
    directory = put_directory(store, [Link(leaf, "leaf", 4)])
    slots = app.state.listing_slots = Slots("listing", 2, 0.05)
    method, path, options = LISTINGS[listing]
    path = path.format(cid=directory)
    if "params" in options:
        options = {"params": {k: v.format(cid=directory) for k, v in options["params"].items()}}

    async def busy_then_free() -> tuple[httpx.Response, httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://cas") as client:
            releases = [await slots.hold() for _ in range(slots.count)]
            try:
                busy = await client.request(method, path, **options)
            finally:
                for release in releases:
                    release()
            return busy, await client.request(method, path, **options)

    busy, free = asyncio.run(busy_then_free())

    assert busy.status_code == 503, busy.text
    assert busy.headers["retry-after"] == "1"
    if method != "HEAD":
        error = busy.json()["error"]
        assert (error["code"], error["details"]) == ("busy", {"slots": 2, "wait_s": 0.05})
    assert free.status_code == 200


@pytest.mark.parametrize("listing", ["gateway-html", "kubo-ls"])
def test_a_directory_with_more_entries_than_a_listing_holds_is_refused_naming_it(
    app: FastAPI, monkeypatch: pytest.MonkeyPatch, listing: str
) -> None:
    """A HAMT may hold millions of names in a few hundred MB of shards, within the read
    budget; every entry was listed in memory and in one answer."""
    monkeypatch.setattr(store_module, "MAX_LISTED_ENTRIES", 10)
    store = store_of(app)
    (leaf,) = store.put_blocks([b"leaf"], RAW, ROBOT, pin=False)
    fits = put_directory(store, [Link(leaf, f"f{i:02d}", 4) for i in range(10)])
    too_many = put_directory(store, [Link(leaf, f"f{i:02d}", 4) for i in range(11)])
    method, path, options = LISTINGS[listing]

    def listed(directory: CID) -> httpx.Response:
        if "params" in options:
            return call(app, method, path, params={"arg": str(directory)})
        return call(app, method, path.format(cid=directory), **options)

    assert listed(fits).status_code == 200
    refused = listed(too_many)
    assert refused.status_code == 400, refused.text
    error = refused.json()["error"]
    assert error["code"] == "too_many_entries"
    assert error["details"] == {"cid": str(too_many), "limit": 10}


def test_ls_lists_at_most_so_many_entries_over_all_its_arguments(
    app: FastAPI, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(store_module, "MAX_LISTED_ENTRIES", 10)
    store = store_of(app)
    (leaf,) = store.put_blocks([b"leaf"], RAW, ROBOT, pin=False)
    six = put_directory(store, [Link(leaf, f"f{i}", 4) for i in range(6)])

    answer = call(app, "POST", "/api/v0/ls", params=[("arg", str(six))] * 2)

    assert answer.status_code == 400, answer.text
    assert answer.json()["error"]["code"] == "too_many_entries"
