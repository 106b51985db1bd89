"""dag-cbor links: found wherever they nest, bad framing refused, no input can make it recurse
or loop; and the DAG walk following them as kubo's recursive pin and ``dag export`` do."""

from __future__ import annotations

import pytest

from robocloud.cid import CID, DAG_CBOR, DAG_PB, RAW, Block, encode_varint
from robocloud.dagcbor import DagCborError, links
from robocloud.dagpb import Link, PBNode
from robocloud.unixfs import UnixfsError, walk_dag


def head(major: int, value: int) -> bytes:
    if value < 24:
        return bytes([major << 5 | value])
    for info, width in ((24, 1), (25, 2), (26, 4), (27, 8)):
        if value < 1 << (8 * width):
            return bytes([major << 5 | info]) + value.to_bytes(width, "big")
    raise ValueError(value)


def text(value: str) -> bytes:
    return head(3, len(value.encode())) + value.encode()


def link(cid: CID) -> bytes:
    binary = b"\x00" + cid.binary
    return head(6, 42) + head(2, len(binary)) + binary


def cbor_block(data: bytes) -> Block:
    return Block(CID.from_block(data, DAG_CBOR), data)


ONE = CID.from_block(b"one")
TWO = CID.from_block(b"two", DAG_PB)
V0 = CID(0, DAG_PB, TWO.multihash)
INLINE = CID(1, RAW, b"\x00" + encode_varint(6) + b"inline")


def test_links_are_found_wherever_they_nest_in_order() -> None:
    document = (
        head(5, 3)
        + text("a")
        + head(4, 3)
        + link(ONE)
        + head(0, 500)
        + head(5, 1)
        + text("deep")
        + link(TWO)
        + text("b")
        + link(V0)
        + text("c")
        + head(4, 2)
        + link(INLINE)
        + link(ONE)
    )
    assert links(document) == [ONE, TWO, V0, INLINE, ONE]


def test_every_kind_of_value_without_links_has_none() -> None:
    values = [
        head(0, 2**64 - 1),
        head(1, 7),
        head(2, 3) + b"abc",
        text("zürich"),
        b"\xf4",
        b"\xf5",
        b"\xf6",
        b"\xf9\x3c\x00",
        b"\xfa\x3f\x80\x00\x00",
        b"\xfb" + bytes(8),
    ]
    assert links(head(4, len(values)) + b"".join(values)) == []


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"", "truncated"),
        (head(4, 2) + head(0, 1), "container of 2 items"),
        (head(2, 5) + b"ab", "5-byte string"),
        (b"\x19\x01", "truncated: the argument"),
        (head(0, 1) + head(0, 2), "1 bytes after"),
        (b"\x9f\x01\xff", "indefinite"),
        (b"\x5f\x41a\xff", "indefinite"),
        (b"\x1c", "reserved"),
        (head(6, 1) + head(0, 0), "tag 1"),
        (head(6, 42) + text("not bytes"), "tag 42 must hold"),
        (head(6, 42) + head(2, 0), "tag 42 must hold"),
        (head(6, 42) + head(2, 37) + b"\x01" + ONE.binary, "tag 42 must hold"),
        (head(6, 42) + head(2, 3) + b"\x00\x01\x55", "invalid link"),
        (head(6, 42) + head(2, 40), "tag 42 must hold"),
        (b"\xf7", "simple value 23"),
        (b"\xf8\x20", "simple value 24"),
    ],
)
def test_what_is_not_dag_cbor_is_refused_saying_why(data: bytes, message: str) -> None:
    with pytest.raises(DagCborError, match=message):
        links(data)


def test_a_huge_claimed_count_is_refused_before_reading_items() -> None:
    """Counted down one item at a time, 2^63 would never end (pytest's timeout would)."""
    for major in (4, 5):
        with pytest.raises(DagCborError, match="items"):
            links(head(major, 2**63) + head(0, 0))


def test_nesting_is_taken_to_go_ipld_primes_depth_and_no_further() -> None:
    """go-ipld-prime (kubo's decoder) takes 1,024 levels of lists and maps and refuses the
    1,025th, empty or not; before, any depth was taken, so cas pinned DAGs kubo refuses."""
    assert links(head(4, 1) * 1023 + head(5, 1) + text("a") + link(ONE)) == [ONE]
    two_branches = head(4, 2) + head(4, 1) * 1022 + head(4, 0) + head(4, 1) * 1023 + link(ONE)
    assert links(two_branches) == [ONE]
    for innermost in (head(4, 0), head(5, 0), head(4, 1) + link(ONE)):
        with pytest.raises(DagCborError, match="byte 1024: nested deeper than 1024 levels"):
            links(head(4, 1) * 1024 + innermost)


def test_nesting_a_million_levels_deep_is_refused_at_the_bound() -> None:
    with pytest.raises(DagCborError, match="nested deeper than 1024"):
        links(head(4, 1) * 1_000_000 + link(ONE))


def test_a_link_is_not_a_level() -> None:
    """A tag 42 over a byte string is a value, not a container."""
    assert links(head(4, 1) * 1023 + head(4, 2) + link(ONE) + link(TWO)) == [ONE, TWO]


def test_the_walk_follows_dag_cbor_links_into_any_codec() -> None:
    leaf = Block(ONE, b"one")
    file_leaf = Block(CID.from_block(b"leaf"), b"leaf")
    node = PBNode([Link(file_leaf.cid, "", 4)], None).encode()
    pb = Block(CID.from_block(node, DAG_PB), node)
    child = cbor_block(head(4, 2) + link(pb.cid) + link(leaf.cid))
    root = cbor_block(head(5, 2) + text("k") + link(child.cid) + text("l") + link(INLINE))
    store = {block.cid: block.data for block in (root, child, pb, file_leaf, leaf)}
    store[INLINE] = b"inline"
    walked = [block.cid for block in walk_dag(root.cid, store.__getitem__, "all")]
    assert walked == [root.cid, child.cid, pb.cid, file_leaf.cid, leaf.cid, INLINE]
    for scope in ("entity", "block"):
        assert [block.cid for block in walk_dag(root.cid, store.__getitem__, scope)] == [root.cid]


def test_the_walk_refuses_a_dag_cbor_block_that_does_not_decode() -> None:
    broken = cbor_block(b"\x9f\xff")
    with pytest.raises(UnixfsError, match=f"{broken.cid} is not a dag-cbor block"):
        list(walk_dag(broken.cid, {broken.cid: broken.data}.__getitem__))


def test_walks_sharing_seen_read_a_common_sub_dag_once() -> None:
    shared = Block(ONE, b"one")
    first = cbor_block(head(4, 1) + link(shared.cid))
    second = cbor_block(head(4, 2) + link(shared.cid) + link(first.cid))
    store = {block.cid: block.data for block in (shared, first, second)}
    reads: list[CID] = []

    def get(cid: CID) -> bytes:
        reads.append(cid)
        return store[cid]

    seen: set[CID] = set()
    list(walk_dag(first.cid, get, "all", seen))
    assert [block.cid for block in walk_dag(second.cid, get, "all", seen)] == [second.cid]
    assert reads == [first.cid, shared.cid, second.cid]
