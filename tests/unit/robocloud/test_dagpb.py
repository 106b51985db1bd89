"""dag-pb: the compatibility vectors decode, the specification's strictness rules hold, and
hostile blocks (huge varints, lengths past the block, too many links) are named and refused.

The byte vectors are those of js-dag-pb's ``test/test-compat.spec.js`` and
``test/test-edges.spec.js`` (mirrored in go-merkledag's ``pb/compat_test.go``); the rules are
those of the IPLD dag-pb specification (``specs/codecs/dag-pb/spec.md``, "Protobuf
Strictness" and "Zero-length blocks").
"""

from __future__ import annotations

from collections import Counter

import pytest

from robocloud.car import CarReader
from robocloud.cid import CID, DAG_PB, RAW
from robocloud.dagpb import (
    MAX_LINKS,
    DagPbError,
    Link,
    PBNode,
    fields,
    len_field,
    read_uint,
    uint_field,
)
from robocloud.errors import FormatError
from robocloud.unixfs import (
    DIRECTORY,
    FILE,
    HAMT_SHARD,
    MURMUR3_X64_64,
    SYMLINK,
    UnixfsData,
    hamt_prefix_width,
)
from tests.unit.robocloud.ipfs_vectors import car_path, vectors

ACID = CID(1, RAW, bytes.fromhex("00050001020304"))
"""The vectors' link target: raw, identity multihash of 0x0001020304 (bafkqabiaaebagba)."""

# (hex bytes, expected Data, expected links as (CID, Name, Tsize)).
COMPATIBLE = [
    ("", None, []),
    ("0a00", b"", []),
    ("0a050001020304", bytes(range(5)), []),
    ("120b0a09015500050001020304", None, [(ACID, "", 0)]),
    ("120d0a090155000500010203041200", None, [(ACID, "", 0)]),
    ("12160a090155000500010203041209736f6d65206e616d65", None, [(ACID, "some name", 0)]),
    ("120d0a090155000500010203041800", None, [(ACID, "", 0)]),
    ("12140a0901550005000102030418ffffffffffffff0f", None, [(ACID, "", 2**53 - 1)]),
    ("12140a09015500050001020304188080808080808010", None, [(ACID, "", 2**53)]),
]


@pytest.mark.parametrize(("encoded", "data", "links"), COMPATIBLE)
def test_the_compatibility_vectors_decode(
    encoded: str, data: bytes | None, links: list[tuple[CID, str, int]]
) -> None:
    node = PBNode.decode(bytes.fromhex(encoded))
    assert node.data == data
    assert [(link.cid, link.name, link.tsize) for link in node.links] == links


def test_the_zero_length_block_is_an_empty_node_with_the_specified_cids() -> None:
    assert PBNode.decode(b"") == PBNode([], None)
    assert str(CID.from_block(b"", DAG_PB, 1)) == (
        "bafybeihdwdcefgh4dqkjv67uzcmw7ojee6xedzdetojuzjevtenxquvyku"
    )
    assert str(CID.from_block(b"", DAG_PB, 0)) == "QmdfTbBqBPQ7VNxZEYEj14VmRuZBkqFbiwReogJgS1zR1n"


def test_data_before_links_is_accepted_as_ipfs_data_exists_in_both_orders() -> None:
    link = len_field(2, len_field(1, ACID.binary))
    node = PBNode.decode(len_field(1, b"\x08\x02") + link + link)
    assert (node.data, len(node.links)) == (b"\x08\x02", 2)


def _link(*parts: bytes) -> bytes:
    return len_field(2, b"".join(parts))


HASH = len_field(1, ACID.binary)
NAME = len_field(2, b"n")
TSIZE = uint_field(3, 7)


@pytest.mark.parametrize(
    ("encoded", "message"),
    [
        (_link(NAME, HASH), "link 0: Hash at byte 5 repeats or comes after Name"),
        (_link(HASH, TSIZE, NAME), "link 0: Name at byte 15 repeats or comes after Tsize"),
        (_link(HASH, HASH), "link 0: Hash at byte 13 repeats or comes after Hash"),
        (_link(HASH, TSIZE, TSIZE), "repeats or comes after Tsize"),
        (_link(NAME), "link 0 has no Hash"),
        (b"\x12\x00", "link 0 has no Hash"),
        (_link(HASH, uint_field(4, 1)), "link 0: field 4 at byte 13 is not in PBLink"),
        (_link(HASH, uint_field(2, 1)), "link 0: Name at byte 13 has wire type 0, not 2"),
        (_link(HASH, len_field(3, b"\x01")), "link 0: Tsize at byte 13 has wire type 2, not 0"),
        (_link(len_field(1, b"")), "link 0: Hash at byte 4: invalid binary CID"),
        (_link(HASH, len_field(2, b"\xff")), "link 0: Name at byte 15 is not UTF-8"),
        (len_field(1, b"a") + len_field(1, b"b"), "a second Data field at byte 3"),
        (_link(HASH) + len_field(1, b"") + _link(HASH), "a link at byte 15 after the Data"),
        (len_field(3, b""), "PBNode field 3 at byte 0: only Data (1) and Links (2)"),
        (uint_field(1, 5), "PBNode field 1 at byte 0 has wire type 0, not 2"),
        (b"\x0d\x00\x00\x00\x00", "PBNode field 1 at byte 0 has wire type 5, not 2"),
    ],
    ids=[
        "link-fields-out-of-order",
        "name-after-tsize",
        "duplicate-hash",
        "duplicate-tsize",
        "missing-hash",
        "empty-link",
        "unknown-link-field",
        "name-as-varint",
        "tsize-as-bytes",
        "hash-not-a-cid",
        "name-not-utf8",
        "duplicate-data",
        "links-data-links",
        "unknown-node-field",
        "data-as-varint",
        "fixed32",
    ],
)
def test_the_specification_strictness_rules_are_enforced(encoded: bytes, message: str) -> None:
    with pytest.raises(DagPbError) as raised:
        PBNode.decode(encoded)
    assert message in str(raised.value)
    assert isinstance(raised.value, FormatError)


def test_a_varint_of_11_bytes_is_refused_naming_its_offset() -> None:
    eleven = b"\xff" * 10 + b"\x01"
    with pytest.raises(DagPbError, match="varint at byte 0 is longer than 10 bytes"):
        PBNode.decode(eleven)
    with pytest.raises(DagPbError, match="varint at byte 1 is longer than 10 bytes"):
        PBNode.decode(b"\x0a" + eleven)
    with pytest.raises(DagPbError, match="varint at byte 1 is longer than 10 bytes"):
        list(fields(b"\x08" + eleven))


def test_a_varint_past_64_bits_is_refused_and_2_to_the_64_minus_1_is_read() -> None:
    assert read_uint(b"\xff" * 9 + b"\x01", 0, 10) == (2**64 - 1, 10)
    with pytest.raises(DagPbError, match="does not fit in 64 bits"):
        read_uint(b"\xff" * 9 + b"\x02", 0, 10)
    with pytest.raises(DagPbError, match="varint at byte 2 runs past the end"):
        read_uint(b"\x00\x00\x80\x80", 2, 4)


@pytest.mark.parametrize(
    ("encoded", "message"),
    [
        (b"\x0a\x05abc", "Data at byte 0 declares 5 bytes but only 3 are left"),
        (
            b"\x0a" + bytes.fromhex("ffffffffffffffffff01"),
            "Data at byte 0 declares 18446744073709551615 bytes",
        ),
        (b"\x12\x64" + HASH, "a link at byte 0 declares 100 bytes but only 11 are left"),
        (
            _link(b"\x0a\x40" + ACID.binary),
            "link 0's Hash at byte 2 declares 64 bytes but only 9 are left",
        ),
    ],
    ids=["data", "data-2^63", "link", "hash-inside-link"],
)
def test_a_length_larger_than_the_block_is_refused(encoded: bytes, message: str) -> None:
    with pytest.raises(DagPbError) as raised:
        PBNode.decode(encoded)
    assert message in str(raised.value)


def test_a_node_may_hold_max_links_links_and_not_one_more() -> None:
    link = _link(HASH, NAME, TSIZE)
    assert len(PBNode.decode(link * MAX_LINKS).links) == MAX_LINKS
    with pytest.raises(DagPbError, match=f"more than {MAX_LINKS} links"):
        PBNode.decode(link * 100_000)


def test_nodes_round_trip_through_the_canonical_encoding() -> None:
    child = CID.from_block(b"child")
    node = PBNode([Link(child, "a", 5), Link(ACID, "", 2**64 - 1)], b"\x08\x02\x18\x05")
    assert PBNode.decode(node.encode()) == node
    assert PBNode.decode(PBNode([], None).encode()) == PBNode([], None)


def test_every_fixture_node_decodes_strictly_and_encodes_back_to_its_block() -> None:
    """kubo's gateway-conformance CARs: files, directories, a symlink, a HAMT's 237 shards."""
    types: Counter[int] = Counter()
    for fixture in vectors()["cars"]:
        with car_path(str(fixture["path"])).open("rb") as car:
            for block in CarReader(car):
                if block.cid.codec != DAG_PB:
                    continue
                node = PBNode.decode(block.data)
                assert node.encode() == block.data
                assert node.data is not None
                unixfs = UnixfsData.decode(node.data)
                types[unixfs.type] += 1
                if unixfs.type == HAMT_SHARD:
                    assert unixfs.hash_type == MURMUR3_X64_64
                    assert hamt_prefix_width(block.cid, unixfs) == 2
    assert types == {DIRECTORY: 11, FILE: 10, SYMLINK: 1, HAMT_SHARD: 237}
