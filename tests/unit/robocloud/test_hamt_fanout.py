"""HAMT shards of any fanout boxo reads: log2(fanout) hash bits per level, most significant first.

kubo writes such shards when ``Import.UnixFSHAMTDirectoryMaxFanout`` is set; js-ipfs-unixfs's
importer (``tests/reference``) writes them with ``shardFanoutBits``. Both are checked: every
name of the reference's shards resolves, and ``sharded_directory`` rebuilds them byte for byte.
"""

from __future__ import annotations

import base64
import json
import subprocess

import pytest

from robocloud.cid import CID, DAG_PB
from robocloud.dagpb import Link, PBNode
from robocloud.directory import (
    PathNotFound,
    list_entries,
    name_hash,
    resolve,
    sharded_directory,
)
from robocloud.unixfs import HAMT_SHARD, MURMUR3_X64_64, UnixfsData, UnixfsError
from tests.reference import REFERENCE, node

ENTRIES = {3: 1_500, 4: 1_500, 5: 1_500, 8: 600, 9: 400, 10: 300}
"""Files besides ``hello.txt`` by fanout bits: enough for sub-shards at every fanout (seven
levels at fanout 8, a second at 1,024), few enough that resolving each name stays quick."""

IMPORT_SHARDED = """
import { importer } from 'ipfs-unixfs-importer'
import { MemoryBlockstore } from 'blockstore-core/memory'
const [count, bits] = process.argv.slice(1).map(Number)
const blocks = {}
class Recording extends MemoryBlockstore {
  put (cid, bytes, options) {
    blocks[cid.toString()] = Buffer.from(bytes).toString('base64')
    return super.put(cid, bytes, options)
  }
}
async function * entries () {
  yield { path: 'dir/hello.txt', content: new TextEncoder().encode('hello\\n') }
  for (let i = 0; i < count; i++) {
    yield { path: `dir/file-${i}.txt`, content: new TextEncoder().encode(`file ${i}\\n`) }
  }
}
const options = {
  cidVersion: 1, rawLeaves: true, shardSplitThresholdBytes: 1, shardFanoutBits: bits
}
let root
for await (const entry of importer(entries(), new Recording(), options)) {
  if (entry.path === 'dir') root = entry.cid
}
console.log(JSON.stringify({ root: root.toString(), blocks }))
"""
"""js-ipfs-unixfs sharding ``hello.txt`` and ``count`` other files at a fanout of 2 ** bits."""


def reference_shard(fanout_bits: int, count: int) -> tuple[CID, dict[CID, bytes]]:
    """The reference importer's HAMT (sharding forced) and every block it wrote."""
    done = subprocess.run(
        [node(), "--input-type=module", "-e", IMPORT_SHARDED, str(count), str(fanout_bits)],
        cwd=REFERENCE,  # where the inline module finds node_modules
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    answer = json.loads(done.stdout)
    blocks = {CID.decode(cid): base64.b64decode(data) for cid, data in answer["blocks"].items()}
    return CID.decode(answer["root"]), blocks


def shard_node(links: list[Link], fanout: int) -> tuple[CID, bytes]:
    """One HAMT shard node over ``links`` (bitfield left empty: lookups go by link name)."""
    data = UnixfsData(HAMT_SHARD, hash_type=MURMUR3_X64_64, fanout=fanout)
    encoded = PBNode(links, data.encode()).encode()
    return CID.from_block(encoded, DAG_PB), encoded


def hash_bits(name: str, start: int, count: int) -> int:
    """Bits ``start`` to ``start + count`` of ``name``'s 64-bit hash, most significant first."""
    value = int.from_bytes(name_hash(name), "big")
    return (value >> (64 - start - count)) & ((1 << count) - 1)


@pytest.mark.parametrize("fanout_bits", list(ENTRIES), ids=lambda bits: f"fanout{1 << bits}")
def test_every_name_of_a_reference_shard_resolves(fanout_bits: int) -> None:
    root, blocks = reference_shard(fanout_bits, ENTRIES[fanout_bits])
    entries = list(list_entries(root, blocks.__getitem__))
    assert len(entries) == ENTRIES[fanout_bits] + 1
    deepest = 0
    for entry in entries:
        found = resolve(root, [entry.name], blocks.__getitem__)
        assert found.cid == entry.cid, entry.name
        assert found.path_blocks[0] == root
        deepest = max(deepest, len(found.path_blocks))
    assert deepest >= 2  # names below sub-shards were resolved too
    with pytest.raises(PathNotFound):
        resolve(root, ["no-such-file.txt"], blocks.__getitem__)
    rebuilt, link = sharded_directory(entries, 1, fanout=1 << fanout_bits)
    assert link.cid == root
    assert {block.cid: block.data for block in rebuilt}.items() <= blocks.items()


def test_a_fanout_16_shard_places_hello_txt_by_four_bits_a_level() -> None:
    """The reported case: listed, but its path was not found (the whole first byte was used).

    ``hello.txt`` hashes to 0xDF..., ``file-8.txt`` to 0xD9... and ``file-32.txt`` to 0xD3...:
    all three share the top bucket D, so they go into a sub-shard placed by the next 4 bits.
    """
    hello = CID.from_block(b"hello\n")
    others = [Link(CID.from_block(f"{i}".encode()), f"file-{i}.txt", 2) for i in range(40)]
    blocks, link = sharded_directory([Link(hello, "hello.txt", 6), *others], 1, fanout=16)
    store = {block.cid: block.data for block in blocks}
    top = {entry.name: entry.cid for entry in PBNode.decode(store[link.cid]).links}
    child = top[f"{hash_bits('hello.txt', 0, 4):X}"]
    below = [entry.name for entry in PBNode.decode(store[child]).links]
    assert below == ["3file-32.txt", "9file-8.txt", "Fhello.txt"]
    found = resolve(link.cid, ["hello.txt"], store.__getitem__)
    assert (found.cid, found.path_blocks) == (hello, [link.cid, child])
    for other in others:
        assert resolve(link.cid, [other.name], store.__getitem__).cid == other.cid


def test_a_shard_below_a_shard_of_another_fanout_takes_its_own_bits() -> None:
    """boxo reads each shard's own fanout: 4 bits at a fanout-16 root, then 8 at its child."""
    leaf = CID.from_block(b"x")
    child, child_block = shard_node([Link(leaf, f"{hash_bits('a', 4, 8):02X}a", 1)], 256)
    root, root_block = shard_node([Link(child, f"{hash_bits('a', 0, 4):X}", 1)], 16)
    store = {root: root_block, child: child_block}
    assert resolve(root, ["a"], store.__getitem__).path_blocks == [root, child]
    assert [entry.name for entry in list_entries(root, store.__getitem__)] == ["a"]


def test_a_hamt_deeper_than_its_64_hash_bits_is_refused_as_boxo_refuses_it() -> None:
    """Fanout 1,024 takes 10 bits a level: six levels use 60, a seventh would need 70."""
    leaf = CID.from_block(b"x")
    store: dict[CID, bytes] = {}
    seventh, block = shard_node([Link(leaf, "000a", 1)], 1024)
    child = seventh
    store[child] = block
    for level in reversed(range(6)):
        child, block = shard_node([Link(child, f"{hash_bits('a', 10 * level, 10):03X}", 1)], 1024)
        store[child] = block
    with pytest.raises(UnixfsError, match="bits up to 70 of a name's 64-bit hash") as raised:
        resolve(child, ["a"], store.__getitem__)
    assert not isinstance(raised.value, PathNotFound)
    assert str(raised.value).startswith(f"the HAMT shard {seventh}: ")


def test_names_sharing_more_hash_bits_than_the_levels_allow_are_not_sharded(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Two names whose hashes differ only in their last 4 bits: fanout 256 places them at the
    eighth level; fanout 1,024 would need a seventh level of 10 bits (boxo cannot either)."""
    hashes = {"a": bytes(8), "b": bytes(7) + b"\x01"}
    monkeypatch.setattr("robocloud.directory.name_hash", hashes.__getitem__)
    entries = [Link(CID.from_block(name.encode()), name, 1) for name in hashes]
    blocks, _ = sharded_directory(entries, 1, fanout=256)
    assert len(blocks) == 8
    with pytest.raises(UnixfsError, match="'a', 'b' share the first 60 bits of their 64-bit"):
        sharded_directory(entries, 1, fanout=1024)


@pytest.mark.parametrize("fanout", [1, 2, 4, 12, 2048])
def test_fanouts_boxo_cannot_load_are_refused(fanout: int) -> None:
    """boxo needs a power of two that fills whole bitfield bytes, at most 1,024."""
    leaf = CID.from_block(b"x")
    root, block = shard_node([Link(leaf, "0a", 1)], fanout)
    with pytest.raises(UnixfsError, match=f"fanout {fanout}"):
        resolve(root, ["a"], {root: block}.__getitem__)
    with pytest.raises(UnixfsError, match=f"fanout {fanout}"):
        sharded_directory([Link(leaf, "a", 1)], 1, fanout=fanout)
