"""DAGs built to hurt the reader: deeper than any importer makes, or lying about their sizes."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from robocloud.cid import CID, DAG_PB, RAW, Block
from robocloud.dagpb import Link, PBNode
from robocloud.unixfs import (
    FILE,
    MAX_DAG_DEPTH,
    UnixfsData,
    UnixfsError,
    assemble_file,
    file_size,
    read_file,
    walk_dag,
)

LEAF = b"x" * 10


def chain(depth: int, leaf: bytes = LEAF) -> tuple[CID, dict[CID, bytes]]:
    """A file whose one leaf hangs ``depth`` single-link nodes below its root."""
    leaf_cid = CID.from_block(leaf, RAW, 1)
    blocks = {leaf_cid: leaf}
    child, size = leaf_cid, len(leaf)
    for _ in range(depth):
        node = PBNode([Link(child, "", size)], UnixfsData(FILE, b"", size, [size]).encode())
        encoded = node.encode()
        child = CID.from_block(encoded, DAG_PB, 1)
        blocks[child] = encoded
    return child, blocks


def lying_root(declared: int, leaf: bytes = LEAF) -> tuple[CID, dict[CID, bytes]]:
    leaf_cid = CID.from_block(leaf, RAW, 1)
    unixfs = UnixfsData(FILE, b"", declared, [declared])
    encoded = PBNode([Link(leaf_cid, "", len(leaf))], unixfs.encode()).encode()
    root = CID.from_block(encoded, DAG_PB, 1)
    return root, {leaf_cid: leaf, root: encoded}


def test_a_chain_at_the_limit_is_read() -> None:
    root, blocks = chain(MAX_DAG_DEPTH)
    assert b"".join(read_file(root, blocks.__getitem__)) == LEAF
    assert len(list(walk_dag(root, blocks.__getitem__))) == MAX_DAG_DEPTH + 1


def test_a_chain_one_deeper_is_refused_naming_the_limit() -> None:
    root, blocks = chain(MAX_DAG_DEPTH + 1)
    with pytest.raises(UnixfsError, match=f"deeper than {MAX_DAG_DEPTH} levels"):
        b"".join(read_file(root, blocks.__getitem__))
    with pytest.raises(UnixfsError, match=f"deeper than {MAX_DAG_DEPTH} levels"):
        list(walk_dag(root, blocks.__getitem__))


def test_a_30000_deep_chain_cannot_crash_even_with_py_ecc_recursion_limit() -> None:
    """py_ecc sets the recursion limit to 100,000 at import: the C stack is then the limit."""
    script = (
        "import sys; sys.setrecursionlimit(100_000)\n"
        "from tests.unit.robocloud.test_unixfs_hostile import chain\n"
        "from robocloud.unixfs import UnixfsError, read_file, walk_dag\n"
        "root, blocks = chain(30_000)\n"
        "for walk in (lambda: b''.join(read_file(root, blocks.__getitem__)),\n"
        "             lambda: list(walk_dag(root, blocks.__getitem__))):\n"
        "    try:\n        walk()\n    except UnixfsError as exc:\n        print('refused')\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, timeout=120, cwd=".", check=False
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split() == [b"refused", b"refused"]


@pytest.mark.parametrize("declared", [len(LEAF) + 1, 10**12, len(LEAF) - 1])
def test_a_root_declaring_another_size_than_its_leaves_hold_fails_reading(declared: int) -> None:
    root, blocks = lying_root(declared)
    assert file_size(root, blocks.__getitem__) == declared
    with pytest.raises(UnixfsError, match=f"holds {len(LEAF)} bytes but its parent"):
        b"".join(read_file(root, blocks.__getitem__))


def test_filesize_disagreeing_with_the_blocksizes_is_refused_from_the_root() -> None:
    leaf_cid = CID.from_block(LEAF, RAW, 1)
    unixfs = UnixfsData(FILE, b"", 999, [len(LEAF)])
    encoded = PBNode([Link(leaf_cid, "", len(LEAF))], unixfs.encode()).encode()
    root = CID.from_block(encoded, DAG_PB, 1)
    with pytest.raises(UnixfsError, match="declares a file of 999 bytes"):
        file_size(root, {root: encoded}.__getitem__)


def test_ranges_of_an_honest_file_are_unaffected() -> None:
    root, blocks = chain(3)
    assert b"".join(read_file(root, blocks.__getitem__, 2, 5)) == LEAF[2:7]


def dfs_blocks(root: CID, blocks: dict[CID, bytes]) -> list[Block]:
    return [Block(cid, blocks[cid]) for cid in _dfs_order(root, blocks)]


def _dfs_order(root: CID, blocks: dict[CID, bytes]) -> list[CID]:
    order: list[CID] = []
    stack = [root]
    while stack:
        cid = stack.pop()
        order.append(cid)
        if cid.codec == DAG_PB:
            stack.extend(reversed([link.cid for link in PBNode.decode(blocks[cid]).links]))
    return order


def test_the_streamed_reader_keeps_the_same_rules(tmp_path: Path) -> None:
    with (tmp_path / "ok").open("w+b") as out:
        root, blocks = chain(MAX_DAG_DEPTH)
        assert assemble_file(root, iter(dfs_blocks(root, blocks)), out, lambda _: None) == 10
    for root, blocks, message in (
        (*chain(MAX_DAG_DEPTH + 1), f"deeper than {MAX_DAG_DEPTH} levels"),
        (*lying_root(len(LEAF) + 1), f"holds {len(LEAF)} bytes but its parent"),
        (*lying_root(len(LEAF) - 1), f"holds {len(LEAF)} bytes but its parent"),
    ):
        with (tmp_path / "bad").open("w+b") as out, pytest.raises(UnixfsError, match=message):
            assemble_file(root, iter(dfs_blocks(root, blocks)), out, lambda _: None)
