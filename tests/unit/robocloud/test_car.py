"""CARv1: the gateway-conformance fixtures round-trip; bad CARs are named and rejected."""

from __future__ import annotations

import io

import pytest

from robocloud.car import MAX_HEADER_BYTES, MAX_ROOTS, CarError, CarReader, encode_header, write_car
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
        (b"\xa1\x62\xff\xfe\x01", "CAR header byte 1: a string that is not UTF-8"),
        (b"\x9b" + b"\xff" * 8, "a CBOR container of 18446744073709551615 items, more than 1024"),
        (b"\x99\x03\xff" + b"\x00" * 10, "truncated CAR header: 1023 items at byte 0"),
        (b"\x7b" + b"\xff" * 8, "truncated CAR header: a 18446744073709551615-byte string"),
        (b"\x1b\xff", "truncated CAR header: the CBOR argument at byte 0"),
        (b"\xa2\x61a\x00\x61a\x01", "CAR header byte 4: the key 'a' repeats"),
        (b"\xa1\x01\x01", "CAR header byte 1: dag-cbor map keys are strings"),
        (b"\xa1\x61a\x9f", "indefinite or reserved CBOR lengths"),
        (b"\xa1\x61a\xf5", "CAR header byte 3: unexpected CBOR major type 7"),
        (b"\xa1\x61a\xd8\x2a\x41\x01", "a CID tag without a 0x00-prefixed byte string"),
        (b"\xa1\x61a\xd8\x2a\x42\x00\x01", "CAR header byte 3: invalid root: invalid binary"),
        (encode_header([]) + b"\x00", "1 bytes after the CAR header's CBOR item"),
    ],
    ids=[
        "deep",
        "deep-roots",
        "not-utf8",
        "huge-count",
        "count-past-the-end",
        "huge-string",
        "truncated-argument",
        "repeated-key",
        "int-key",
        "indefinite",
        "simple-value",
        "cid-tag-without-prefix",
        "cid-tag-bad-cid",
        "trailing-bytes",
    ],
)
def test_hostile_headers_are_car_errors(header: bytes, message: str) -> None:
    stream = io.BytesIO(encode_varint(len(header)) + header)
    with pytest.raises(CarError) as raised:
        CarReader(stream)
    assert message in str(raised.value)


def test_too_many_roots_are_refused() -> None:
    cid = CID.from_block(b"x")
    header = encode_header([cid] * (MAX_ROOTS + 1))
    with pytest.raises(CarError, match="1025 items, more than 1024"):
        CarReader(io.BytesIO(encode_varint(len(header)) + header))
    header = encode_header([cid] * MAX_ROOTS)
    assert len(CarReader(io.BytesIO(encode_varint(len(header)) + header)).roots) == MAX_ROOTS


def test_an_oversized_header_is_refused_before_it_is_read() -> None:
    with pytest.raises(CarError, match=f"more than {MAX_HEADER_BYTES}"):
        CarReader(io.BytesIO(encode_varint(MAX_HEADER_BYTES + 1)))


HEADER = encode_varint(len(encode_header([]))) + encode_header([])


@pytest.mark.parametrize(
    ("tail", "message"),
    [
        (b"\xff" * 10 + b"\x01", f"CAR varint at byte {len(HEADER)} is longer than 9 bytes"),
        (b"\x81\x00", f"CAR varint at byte {len(HEADER)} is not minimally encoded"),
        (b"\x81", f"truncated CAR: the varint at byte {len(HEADER)} ends early"),
        (b"\x05\x01", f"truncated CAR: 5 bytes due at byte {len(HEADER) + 1}, 1 there"),
    ],
    ids=["11-bytes", "not-minimal", "truncated-varint", "truncated-section"],
)
def test_bad_section_framing_is_named_with_its_offset(tail: bytes, message: str) -> None:
    with pytest.raises(CarError) as raised:
        list(CarReader(io.BytesIO(HEADER + tail)))
    assert message in str(raised.value)


def test_a_bad_block_names_its_section_offset() -> None:
    good = Block(CID.from_block(b"good"), b"good")
    car = car_with([good, Block(good.cid, b"evil")])
    second = len(car) - (1 + len(good.cid.binary) + 4)
    with pytest.raises(CarError, match=f"section at byte {second}: block does not match"):
        list(CarReader(io.BytesIO(car)))
