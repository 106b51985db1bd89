"""What a pin keeps, against a real cas: garbage collection follows every link of a pinned DAG
(a CID's codec as well as its multihash, identity CIDs, dag-cbor), pinning needs whole DAGs
and is all or nothing, and identity blocks take no room in the store."""

from __future__ import annotations

import io
import json
from typing import Any

import httpx
import pytest

from robocloud.car import CarReader, write_car
from robocloud.cas import Cas
from robocloud.cid import CID, DAG_CBOR, DAG_JSON, DAG_PB, RAW, Block, encode_varint
from robocloud.client import ServiceClient
from robocloud.dagpb import Link, PBNode
from robocloud.errors import ApiError
from robocloud.identity import Identity
from robocloud.unixfs import DIRECTORY, FILE, UnixfsData, import_bytes
from tests.conftest import ServiceFactory
from tests.integration.services.cas.conftest import (
    QUIET_GC,
    error_of,
    multipart,
    repo_stat,
    store_unchanged,
)
from tests.procs import ServiceProcess

FILE_DATA = bytes(i % 253 for i in range(700_000))  # a dag-pb root over three raw leaves


@pytest.fixture
def cas_service(service_factory: ServiceFactory) -> ServiceProcess:
    """A cas whose garbage collection spares nothing for age: only pins keep blocks."""
    return service_factory("cas", {**QUIET_GC, "ROBOCLOUD_CAS_GC_GRACE_S": "0"})


def gc(client: ServiceClient) -> set[str]:
    response = client.request("POST", "/api/v0/repo/gc")
    return {json.loads(line)["Key"]["/"] for line in response.text.splitlines()}


def dag_import(client: ServiceClient, roots: list[CID], blocks: list[Block]) -> list[Any]:
    body, content_type = multipart(("dag.car", b"".join(write_car(roots, blocks))))
    response = client.request(
        "POST", "/api/v0/dag/import", content=body, headers={"Content-Type": content_type}
    )
    return [json.loads(line)["Root"] for line in response.text.splitlines()]


def block_put(client: ServiceClient, data: bytes, codec: str, *, pin: bool) -> httpx.Response:
    body, content_type = multipart(("block", data))
    return client.request(
        "POST",
        "/api/v0/block/put",
        params={"cid-codec": codec, "pin": str(pin).lower()},
        content=body,
        headers={"Content-Type": content_type},
    )


def exported(url: str, root: CID) -> list[CID]:
    response = httpx.post(f"{url}/api/v0/dag/export", params={"arg": str(root)})
    assert response.status_code == 200, response.text
    return [block.cid for block in CarReader(io.BytesIO(response.content))]


def raw(data: bytes) -> Block:
    return Block(CID.from_block(data), data)


def pb(links: list[Link], data: bytes) -> Block:
    encoded = PBNode(links, data).encode()
    return Block(CID.from_block(encoded, DAG_PB), encoded)


def file_node(child: Block) -> Block:
    size = len(child.data)
    return pb(
        [Link(child.cid, "", size)], UnixfsData(FILE, filesize=size, blocksizes=[size]).encode()
    )


def cbor_links_to(child: CID) -> Block:
    """dag-cbor ``{"child": <CID>}``."""
    binary = b"\x00" + child.binary
    document = b"\xa1\x65child\xd8\x2a\x58" + bytes([len(binary)]) + binary
    return Block(CID.from_block(document, DAG_CBOR), document)


def test_a_raw_alias_pinned_by_one_robot_leaves_anothers_file_whole(
    cas_service: ServiceProcess, signed: ServiceClient
) -> None:
    """Robot A pins the raw-codec CID of robot B's file root (the same multihash); gc used
    to mark that multihash as a leaf and then skip B's dag-pb root, deleting B's leaves."""
    blocks, root = import_bytes(FILE_DATA)
    alias = CID(1, RAW, root.multihash)
    root_bytes = next(block.data for block in blocks if block.cid == root)
    assert dag_import(signed, [alias], [Block(alias, root_bytes)]) == [
        {"Cid": {"/": str(alias)}, "PinErrorMsg": ""}
    ]
    with Cas(cas_service.url, Identity.generate(), retries=0) as victim:
        assert victim.add_bytes(FILE_DATA) == root
        assert gc(signed) == set()
        assert victim.get(root) == FILE_DATA
    assert repo_stat(cas_service.url)["NumObjects"] == len(blocks)


def test_gc_follows_an_alias_in_the_same_dag_and_an_identity_inlined_node(
    cas_service: ServiceProcess, signed: ServiceClient
) -> None:
    """One directory links a node under its dag-pb CID and its raw alias; another links a
    dag-pb node inlined as an identity CID: the children of both are pinned content."""
    child_a, child_b = raw(b"precious child data A"), raw(b"precious child data B")
    node_a = file_node(child_a)
    alias = CID(1, RAW, node_a.cid.multihash)
    root_a = pb([Link(node_a.cid, "f", 0), Link(alias, "g", 0)], UnixfsData(DIRECTORY).encode())
    inner = file_node(child_b).data
    inlined = CID(1, DAG_PB, b"\x00" + encode_varint(len(inner)) + inner)
    root_b = pb([Link(inlined, "f", 0)], UnixfsData(DIRECTORY).encode())
    dag_import(signed, [root_a.cid, root_b.cid], [root_a, node_a, child_a, root_b, child_b])
    assert gc(signed) == set()
    assert exported(cas_service.url, root_a.cid) == [root_a.cid, node_a.cid, child_a.cid, alias]
    assert child_b.cid in exported(cas_service.url, root_b.cid)
    response = httpx.get(f"{cas_service.url}/ipfs/{root_b.cid}/f")
    assert (response.status_code, response.content) == (200, child_b.data)


def test_dag_cbor_links_are_pinned_exported_and_kept(
    cas_service: ServiceProcess, signed: ServiceClient
) -> None:
    child, loose = raw(b"cbor child payload"), raw(b"linked from nothing")
    root = cbor_links_to(child.cid)
    dag_import(signed, [root.cid], [root, child, loose])
    assert exported(cas_service.url, root.cid) == [root.cid, child.cid]
    car = httpx.get(f"{cas_service.url}/ipfs/{root.cid}", params={"format": "car"})
    assert [block.cid for block in CarReader(io.BytesIO(car.content))] == [root.cid, child.cid]
    assert gc(signed) == {str(loose.cid)}
    assert signed.request("POST", "/api/v0/block/get", params={"arg": str(child.cid)}).content == (
        child.data
    )


def nested_link_to(child: CID, depth: int, codec: str) -> Block:
    """The link ``depth`` levels down: dag-json ``{"a": {"a": ... {"/": <CID>}}}`` (the link
    is a map, a level of its own), or dag-cbor ``[[... <CID>]]`` (the link is a tag)."""
    if codec == "dag-json":
        document = b'{"a":' * (depth - 1) + f'{{"/":"{child}"}}'.encode() + b"}" * (depth - 1)
        return Block(CID.from_block(document, DAG_JSON), document)
    binary = b"\x00" + child.binary
    document = b"\x81" * depth + b"\xd8\x2a\x58" + bytes([len(binary)]) + binary
    return Block(CID.from_block(document, DAG_CBOR), document)


@pytest.mark.parametrize("codec", ["dag-json", "dag-cbor"])
def test_a_dag_as_deep_as_kubo_takes_is_pinned_and_kept_and_one_deeper_refused(
    cas_service: ServiceProcess, signed: ServiceClient, codec: str
) -> None:
    """go-ipld-prime decodes dag-json and dag-cbor 1,024 levels deep and no deeper. cas
    refused dag-json past 64 (400 invalid_dag), so such a DAG could be pinned on kubo and
    not here; and took dag-cbor at any depth, so it pinned DAGs kubo refuses."""
    child, loose = raw(f"{codec} child payload".encode()), raw(b"left for the collector")
    root = nested_link_to(child.cid, 1024, codec)
    assert dag_import(signed, [root.cid], [root, child, loose]) == [
        {"Cid": {"/": str(root.cid)}, "PinErrorMsg": ""}
    ]
    assert exported(cas_service.url, root.cid) == [root.cid, child.cid]
    assert gc(signed) == {str(loose.cid)}
    too_deep = nested_link_to(child.cid, 1025, codec)
    with store_unchanged(cas_service), pytest.raises(ApiError) as raised:
        dag_import(signed, [too_deep.cid], [too_deep])
    error = error_of(raised, 400, "invalid_dag")
    assert "nested deeper than 1024 levels" in error.message


def test_pin_add_of_a_dag_cbor_root_needs_what_it_links(
    cas_service: ServiceProcess, signed: ServiceClient
) -> None:
    missing = raw(b"never uploaded")
    root = cbor_links_to(missing.cid)
    block_put(signed, root.data, "dag-cbor", pin=False)
    with store_unchanged(cas_service), pytest.raises(ApiError) as raised:
        signed.request("POST", "/api/v0/pin/add", params={"arg": str(root.cid)})
    error = error_of(raised, 404, "block_not_found")
    assert error.details == {"cid": str(root.cid), "missing": str(missing.cid)}


@pytest.mark.parametrize("codec", ["dag-pb", "dag-cbor"])
def test_block_put_with_pin_refuses_a_dag_whose_child_is_missing(
    cas_service: ServiceProcess, signed: ServiceClient, codec: str
) -> None:
    child = raw(b"never uploaded child")
    node = file_node(child) if codec == "dag-pb" else cbor_links_to(child.cid)
    with store_unchanged(cas_service), pytest.raises(ApiError) as raised:
        block_put(signed, node.data, codec, pin=True)
    error = error_of(raised, 404, "block_not_found")
    assert error.details == {"cid": str(node.cid), "missing": str(child.cid)}
    assert str(node.cid) in error.message
    assert repo_stat(cas_service.url)["NumObjects"] == 0
    block_put(signed, child.data, "raw", pin=False)
    block_put(signed, node.data, codec, pin=True)
    pins = httpx.post(f"{cas_service.url}/api/v0/pin/ls").json()["Keys"]
    assert list(pins) == [str(node.cid)]


def test_pin_add_is_all_or_nothing(cas_service: ServiceProcess, signed: ServiceClient) -> None:
    present, missing = raw(b"block a"), raw(b"nobody has this")
    block_put(signed, present.data, "raw", pin=False)
    with store_unchanged(cas_service), pytest.raises(ApiError) as raised:
        signed.request(
            "POST", "/api/v0/pin/add", params=[("arg", str(present.cid)), ("arg", str(missing.cid))]
        )
    error = error_of(raised, 404, "block_not_found")
    assert error.details == {"cid": str(missing.cid), "missing": str(missing.cid)}
    assert httpx.post(f"{cas_service.url}/api/v0/pin/ls").json() == {"Keys": {}}


def test_identity_blocks_of_a_car_are_not_stored(
    cas_service: ServiceProcess, signed: ServiceClient
) -> None:
    inline = CID(1, RAW, b"\x00" + encode_varint(6) + b"inline")
    stored = raw(b"an ordinary block")
    before = repo_stat(cas_service.url)
    roots = dag_import(signed, [inline, stored.cid], [Block(inline, b"inline"), stored])
    assert [root["PinErrorMsg"] for root in roots] == ["", ""]
    assert repo_stat(cas_service.url)["NumObjects"] == before["NumObjects"] + 1
    assert httpx.get(f"{cas_service.url}/ipfs/{inline}?format=raw").content == b"inline"
    assert gc(signed) == set()
