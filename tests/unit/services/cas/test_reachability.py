"""What a pin keeps, in process: garbage collection walks by codec as well as multihash,
through identity CIDs and dag-cbor and dag-json links; pinning is all or nothing and needs
whole DAGs; identity blocks are never stored."""

from __future__ import annotations

import io
import time

import pytest

from robocloud.car import write_car
from robocloud.cid import CID, DAG_CBOR, DAG_JSON, DAG_PB, RAW, Block, encode_varint
from robocloud.dagpb import Link, PBNode
from robocloud.unixfs import DIRECTORY, FILE, UnixfsData
from services.cas.store import ContentStore, DagIncomplete

ALICE = "0x" + "a1" * 20
BOB = "0x" + "b0" * 20


def raw(data: bytes) -> Block:
    return Block(CID.from_block(data), data)


def file_node(child: Block) -> bytes:
    size = len(child.data)
    unixfs = UnixfsData(FILE, filesize=size, blocksizes=[size]).encode()
    return PBNode([Link(child.cid, "", size)], unixfs).encode()


def put(store: ContentStore, *blocks: Block) -> None:
    with store.blocks.stage() as staging:
        for block in blocks:
            staging.add(block.cid, block.data)
        staging.commit()


def collect(store: ContentStore) -> set[bytes]:
    return {cid.multihash for cid in store.collect_garbage(grace_s=0, now=time.time() + 1)}


def test_a_raw_alias_pinned_first_does_not_hide_the_dag_pb_links(store: ContentStore) -> None:
    child = raw(b"bob's leaf")
    node = file_node(child)
    root = CID.from_block(node, DAG_PB)
    alias = CID(1, RAW, root.multihash)
    put(store, Block(root, node), child)
    store.pin([alias], ALICE)
    store.pin([root], BOB)
    assert collect(store) == set()
    assert store.get_block(child.cid) == child.data


def test_an_identity_dag_pb_node_has_its_children_kept(store: ContentStore) -> None:
    child = raw(b"under an inlined node")
    inner = file_node(child)
    inlined = CID(1, DAG_PB, b"\x00" + encode_varint(len(inner)) + inner)
    directory = PBNode([Link(inlined, "f", 0)], UnixfsData(DIRECTORY).encode()).encode()
    root = Block(CID.from_block(directory, DAG_PB), directory)
    put(store, root, child)
    store.pin([root.cid], ALICE)
    assert collect(store) == set()
    assert store.get_block(child.cid) == child.data


def test_dag_cbor_links_are_followed_and_what_they_leave_is_collected(
    store: ContentStore,
) -> None:
    kept, loose = raw(b"linked from dag-cbor"), raw(b"linked from nothing")
    binary = b"\x00" + kept.cid.binary
    document = b"\xa1\x64kept\xd8\x2a\x58" + bytes([len(binary)]) + binary
    root = Block(CID.from_block(document, DAG_CBOR), document)
    put(store, root, kept, loose)
    store.pin([root.cid], ALICE)
    assert collect(store) == {loose.cid.multihash}
    assert store.get_block(kept.cid) == kept.data


def test_dag_json_links_are_followed_and_what_they_leave_is_collected(
    store: ContentStore,
) -> None:
    kept, loose = raw(b"linked from dag-json"), raw(b"linked from nothing either")
    document = b'{"kept":{"/":"' + str(kept.cid).encode() + b'"}}'
    root = Block(CID.from_block(document, DAG_JSON), document)
    put(store, root, kept, loose)
    store.pin([root.cid], ALICE)
    assert collect(store) == {loose.cid.multihash}
    assert store.get_block(kept.cid) == kept.data


def test_put_blocks_with_pin_refuses_an_incomplete_dag_and_stores_nothing(
    store: ContentStore,
) -> None:
    child = raw(b"never sent")
    node = file_node(child)
    with pytest.raises(DagIncomplete) as raised:
        store.put_blocks([node], DAG_PB, ALICE, pin=True)
    assert (raised.value.root, raised.value.missing) == (CID.from_block(node, DAG_PB), child.cid)
    assert (store.usage(), store.pinned()) == ((0, 0), {})


def test_put_blocks_with_pin_counts_the_blocks_of_the_same_request(store: ContentStore) -> None:
    child = raw(b"sent alongside")
    node = Block(CID.from_block(file_node(child), DAG_PB), file_node(child))
    put(store, child)
    (cid,) = store.put_blocks([node.data], DAG_PB, ALICE, pin=True)
    assert store.pinned() == {cid: frozenset({ALICE})}


def test_pinning_several_roots_is_all_or_nothing(store: ContentStore) -> None:
    present, missing = raw(b"here"), raw(b"nowhere")
    put(store, present)
    with pytest.raises(DagIncomplete) as raised:
        store.pin([present.cid, missing.cid], ALICE)
    assert raised.value.missing == missing.cid
    assert store.pinned() == {}
    store.pin([present.cid, present.cid], ALICE)
    assert store.pinned() == {present.cid: frozenset({ALICE})}


def test_identity_blocks_are_never_stored(store: ContentStore) -> None:
    inline = CID(1, RAW, b"\x00" + encode_varint(6) + b"inline")
    assert not store.blocks.put(inline, b"inline")
    car = b"".join(write_car([inline], [Block(inline, b"inline")]))
    with store.blocks.stage() as staging:
        assert store.import_car(staging, io.BytesIO(car)) == [inline]
        assert inline not in staging
        staging.commit()
    assert store.usage() == (0, 0)
    assert store.get_block(inline) == b"inline"
