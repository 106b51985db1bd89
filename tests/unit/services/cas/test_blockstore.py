"""The pack blockstore: commit or nothing, re-hash on read, delete and compact, reload."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from robocloud.cid import CID, CIDError
from services.cas.blockstore import BlockNotFound, Blockstore


def block(text: str) -> tuple[CID, bytes]:
    data = text.encode() * 1000
    return CID.from_block(data), data


def commit_all(store: Blockstore, blocks: list[tuple[CID, bytes]]) -> None:
    with store.stage() as staged:
        for cid, data in blocks:
            staged.add(cid, data)
        staged.commit()


def test_staged_blocks_are_invisible_until_commit(tmp_path: Path) -> None:
    store = Blockstore(tmp_path)
    cid, data = block("a")
    with store.stage() as staged:
        staged.add(cid, data)
        assert cid in staged
        assert not store.has(cid)
        assert staged.get(cid) == data
        assert staged.commit() == 1
    assert store.get(cid) == data


def test_discarded_upload_leaves_no_file(tmp_path: Path) -> None:
    store = Blockstore(tmp_path)
    cid, data = block("a")
    with store.stage() as staged:
        staged.add(cid, data)
    assert not store.has(cid)
    assert list((tmp_path / "packs").iterdir()) == []


def test_a_pack_without_index_is_dropped_at_start(tmp_path: Path) -> None:
    store = Blockstore(tmp_path)
    cid, data = block("a")
    staged = store.stage()
    staged.add(cid, data)
    staged._file.flush()  # the process dies here: written, never committed
    reopened = Blockstore(tmp_path)
    assert not reopened.has(cid)
    assert list((tmp_path / "packs").iterdir()) == []
    staged._file.close()  # what the kill would have closed


def test_committed_blocks_survive_reopening(tmp_path: Path) -> None:
    store = Blockstore(tmp_path)
    blocks = [block(t) for t in "abc"]
    commit_all(store, blocks)
    reopened = Blockstore(tmp_path)
    for cid, data in blocks:
        assert reopened.get(cid) == data
    assert reopened.usage() == (3, sum(len(d) for _, d in blocks))


def test_put_refuses_bytes_that_do_not_match(tmp_path: Path) -> None:
    store = Blockstore(tmp_path)
    cid, _ = block("a")
    with pytest.raises(CIDError):
        store.put(cid, b"other bytes")
    assert not store.has(cid)


def test_a_rotten_block_is_quarantined_and_reported(tmp_path: Path) -> None:
    reported: list[CID] = []
    store = Blockstore(tmp_path, on_corrupt=lambda cid, _: reported.append(cid))
    cid, data = block("a")
    store.put(cid, data)
    location = store.locate(cid)
    with store.pack_path(location.pack).open("r+b") as pack:
        pack.seek(location.offset + 10)
        pack.write(b"X")
    with pytest.raises(BlockNotFound) as miss:
        store.get(cid)
    assert "quarantined" in miss.value.reason
    assert reported == [cid]
    assert not store.has(cid)
    assert not Blockstore(tmp_path).has(cid)
    [quarantined] = (tmp_path / "quarantine").iterdir()
    assert quarantined.read_bytes() != data
    assert len(quarantined.read_bytes()) == len(data)


def test_delete_then_compact_reclaims_space_and_keeps_the_rest(tmp_path: Path) -> None:
    store = Blockstore(tmp_path)
    blocks = [block(t) for t in "abcd"]
    commit_all(store, blocks)
    store.delete([blocks[0][0].multihash, blocks[1][0].multihash, blocks[2][0].multihash])
    assert store.compact() == 3 * len(blocks[0][1])
    assert store.get(blocks[3][0]) == blocks[3][1]
    assert [p.suffix for p in sorted((tmp_path / "packs").iterdir())] == [".idx", ".pack"]
    reopened = Blockstore(tmp_path)
    assert reopened.usage() == (1, len(blocks[3][1]))
    assert not reopened.has(blocks[0][0])


def test_deleting_every_block_of_a_pack_removes_it(tmp_path: Path) -> None:
    store = Blockstore(tmp_path)
    cid, data = block("a")
    store.put(cid, data)
    store.delete([cid.multihash])
    assert list((tmp_path / "packs").iterdir()) == []


def test_the_index_is_plain_json(tmp_path: Path) -> None:
    store = Blockstore(tmp_path)
    cid, data = block("a")
    store.put(cid, data)
    [index] = (tmp_path / "packs").glob("*.idx")
    assert json.loads(index.read_bytes()) == [[cid.multihash.hex(), 0, len(data)]]
