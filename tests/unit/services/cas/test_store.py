"""The content store in process: files, DAGs, CARs, pins and garbage collection on real files."""

from __future__ import annotations

import io
import time

import pytest

from robocloud.car import write_car
from robocloud.cid import CID, DAG_PB, RAW, Block
from robocloud.dagpb import PBNode
from robocloud.unixfs import DIRECTORY, ImportParams, UnixfsData, import_bytes
from services.cas.store import (
    BlockUnavailable,
    CarRejected,
    ContentStore,
    DagIncomplete,
    NotAFile,
    UnknownScope,
    UnpinnedArgument,
)

ROBOT = "0x" + "ab" * 20
DATA = bytes(range(256)) * 2000  # two chunks: a root and two leaves
SMALL = ImportParams(chunk_size=262_144)


def put_file(store: ContentStore, data: bytes = DATA) -> tuple[CID, list[Block]]:
    blocks, root = import_bytes(data, SMALL)
    for codec in (RAW, DAG_PB):
        chosen = [block.data for block in blocks if block.cid.codec == codec]
        if chosen:
            store.put_blocks(chosen, codec, ROBOT, pin=False)
    return root, blocks


def test_a_file_reads_back_whole_and_in_ranges(store: ContentStore) -> None:
    root, _ = put_file(store)
    assert store.file_size(root) == len(DATA)
    assert b"".join(store.read(root)) == DATA
    assert b"".join(store.read(root, 262_100, 100)) == DATA[262_100:262_200]


def test_an_unknown_block_is_unavailable_naming_it(store: ContentStore) -> None:
    missing = CID.from_block(b"nobody has this")
    with pytest.raises(BlockUnavailable) as raised:
        store.get_block(missing)
    assert raised.value.cid == missing
    assert "no peer" not in str(raised.value)


def test_a_directory_is_not_a_file(store: ContentStore) -> None:
    directory = PBNode([], UnixfsData(DIRECTORY).encode()).encode()
    (cid,) = store.put_blocks([directory], DAG_PB, ROBOT, pin=False)
    with pytest.raises(NotAFile) as raised:
        store.file_size(cid)
    assert raised.value.cid == cid


def test_blocks_of_a_dag_come_in_car_order_and_scopes_are_checked(store: ContentStore) -> None:
    root, blocks = put_file(store)
    walked = list(store.blocks_of(root, "all"))
    assert walked[0].cid == root
    assert {block.cid for block in walked} == {block.cid for block in blocks}
    assert [block.cid for block in store.blocks_of(root, "block")] == [root]
    with pytest.raises(UnknownScope):
        list(store.blocks_of(root, "everything"))


def test_a_car_with_one_forged_block_is_rejected_and_nothing_committed(
    store: ContentStore,
) -> None:
    blocks, root = import_bytes(DATA, SMALL)
    forged = [blocks[0], Block(blocks[1].cid, b"forged"), *blocks[2:]]
    car = b"".join(write_car([root], forged))
    with store.blocks.stage() as staging, pytest.raises(CarRejected):
        store.import_car(staging, io.BytesIO(car))
    assert store.usage() == (0, 0)


def test_missing_block_sees_staged_blocks(store: ContentStore) -> None:
    blocks, root = import_bytes(DATA, SMALL)
    with store.blocks.stage() as staging:
        for block in blocks[:-1]:
            staging.add(block.cid, block.data)
        assert store.missing_block(root, staging) == blocks[-1].cid
        staging.add(blocks[-1].cid, blocks[-1].data)
        assert store.missing_block(root, staging) is None


def test_pinning_needs_the_whole_dag(store: ContentStore) -> None:
    blocks, root = import_bytes(DATA, SMALL)
    store.put_blocks(
        [block.data for block in blocks if block.cid.codec == DAG_PB], DAG_PB, ROBOT, pin=False
    )
    with pytest.raises(DagIncomplete) as raised:
        store.pin([root], ROBOT)
    assert (raised.value.root, raised.value.missing.codec) == (root, RAW)
    assert store.pinned() == {}
    put_file(store)
    store.pin([root], ROBOT)
    assert store.pinned([root]) == {root: frozenset({ROBOT})}


def test_a_pin_listing_of_an_unpinned_cid_names_it(store: ContentStore) -> None:
    stranger = CID.from_block(b"unpinned")
    with pytest.raises(UnpinnedArgument) as raised:
        store.pinned([stranger])
    assert raised.value.cid == stranger


def test_garbage_collection_keeps_pinned_dags_and_young_blocks(store: ContentStore) -> None:
    pinned, pinned_blocks = put_file(store)
    store.pin([pinned], ROBOT)
    unpinned, _ = put_file(store, b"collect me" * 1000)
    assert store.collect_garbage(grace_s=3600) == []
    removed = {cid.multihash for cid in store.collect_garbage(grace_s=0, now=time.time() + 1)}
    assert unpinned.multihash in removed  # answered as raw CIDs: the store keeps multihashes
    assert not {block.cid.multihash for block in pinned_blocks} & removed
    assert b"".join(store.read(pinned)) == DATA
    with pytest.raises(BlockUnavailable):
        store.get_block(unpinned)


def test_unpinning_then_collecting_frees_the_dag(store: ContentStore) -> None:
    root, _ = put_file(store)
    store.pin([root], ROBOT)
    store.unpin([root], ROBOT)
    assert store.pinned() == {}
    removed = store.collect_garbage(grace_s=0, now=time.time() + 1)
    assert root.multihash in {cid.multihash for cid in removed}
    assert store.usage()[0] == 0
