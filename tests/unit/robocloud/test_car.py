"""CARv1: the gateway-conformance fixtures round-trip; bad CARs are named and rejected."""

from __future__ import annotations

import io

import pytest

from robocloud.car import MAX_ROOTS, CarError, CarReader, encode_header, write_car
from robocloud.cid import CID, Block, encode_varint
from tests.unit.robocloud.ipfs_vectors import car_path, vectors


@pytest.mark.parametrize("fixture", vectors()["cars"], ids=lambda c: c["path"].rsplit("/", 1)[-1])
def test_fixture_reads_verified_and_writes_back_byte_identical(fixture: dict[str, object]) -> None:
    raw = car_path(str(fixture["path"])).read_bytes()
    reader = CarReader(io.BytesIO(raw))
    blocks = list(reader)
    assert [str(root) for root in reader.roots] == fixture["roots"]
    assert len(blocks) == fixture["blocks"]
    assert b"".join(write_car(reader.roots, blocks)) == raw


def car_with(blocks: list[Block]) -> bytes:
    return b"".join(write_car([blocks[0].cid], blocks))


def test_block_that_does_not_match_its_cid_is_named() -> None:
    good = Block(CID.from_block(b"good"), b"good")
    liar = Block(CID.from_block(b"claimed"), b"actual")
    reader = CarReader(io.BytesIO(car_with([good, liar])))
    iterator = iter(reader)
    assert next(iterator) == good
    with pytest.raises(CarError, match=str(liar.cid)):
        next(iterator)


@pytest.mark.parametrize(
    ("car", "message"),
    [
        (b"", "missing"),
        (encode_varint(5) + b"\xa1abc", "truncated"),
        (encode_varint(3) + b"\x82\x01\x02", "version"),
        (car_with([Block(CID.from_block(b"a"), b"a")])[:-1], "truncated"),
    ],
    ids=["empty", "short-header", "not-a-map", "short-block"],
)
def test_malformed_car_is_rejected(car: bytes, message: str) -> None:
    with pytest.raises(CarError, match=message):
        list(CarReader(io.BytesIO(car)))


def test_header_is_dag_cbor_with_keys_in_canonical_order() -> None:
    root = CID.from_block(b"a")
    header = encode_header([root])
    assert header.startswith(b"\xa2eroots\x81\xd8\x2a\x58\x25\x00")
    assert header.endswith(b"gversion\x01")


def test_oversized_section_is_refused_before_reading_it() -> None:
    car = encode_varint(len(encode_header([]))) + encode_header([]) + encode_varint(1 << 30)
    with pytest.raises(CarError, match="exceeds"):
        list(CarReader(io.BytesIO(car)))


@pytest.mark.parametrize(
    ("header", "message"),
    [
        (b"\x81" * 100_000, "nested deeper than 8 levels"),
        (b"\xa1\x65roots" + b"\x81" * 50 + b"\x00", "nested deeper than 8 levels"),
        (b"\xa1\x62\xff\xfe\x01", "not UTF-8"),
        (b"\x9b" + b"\xff" * 8, "truncated CAR header"),
    ],
    ids=["deep", "deep-roots", "not-utf8", "huge-count"],
)
def test_hostile_headers_are_car_errors(header: bytes, message: str) -> None:
    stream = io.BytesIO(encode_varint(len(header)) + header)
    with pytest.raises(CarError, match=message):
        CarReader(stream)


def test_too_many_roots_are_refused() -> None:
    cid = CID.from_block(b"x")
    header = encode_header([cid] * (MAX_ROOTS + 1))
    with pytest.raises(CarError, match="more than 1024"):
        CarReader(io.BytesIO(encode_varint(len(header)) + header))
