"""CARs: the gateway-conformance fixtures round-trip; bad CARs are named and rejected; CARv2
is read (the spec's own fixture, and CARv1s wrapped here) and each malformed CARv2 is named."""

from __future__ import annotations

import io

import pytest

from robocloud.car import (
    CARV2_PRAGMA,
    CARV2_PREFIX_BYTES,
    MAX_HEADER_BYTES,
    MAX_ROOTS,
    MAX_SECTION_BYTES,
    CarError,
    CarReader,
    encode_header,
    write_car,
)
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


# The CARv2 spec's fixture, written by go-car: ipld/ipld@7bf3ba14bc9cc382440a1ad244ed827002412432
# specs/transport/car/fixture/carv2-basic/carv2-basic.car (715 bytes, sha256 51f2b35c...dbca62;
# MIT/Apache-2.0). Data offset 51, data size 448, then an index at byte 499 (an early go-car
# layout no reader here needs). Its carv2-basic.json lists the roots and blocks below.
SPEC_CARV2_BASIC = bytes.fromhex(
    "0aa16776657273696f6e02000000000000000000000000000000003300000000000000c001000000000000f3"
    "0100000000000038a265726f6f747381d82a5823001220fb16f5083412ef1371d031ed4aa239903d84efdadf"
    "1ba3cd678e6475b1a232f86776657273696f6e01511220fb16f5083412ef1371d031ed4aa239903d84efdadf"
    "1ba3cd678e6475b1a232f8122d0a221220d9c0d5376d26f1931f7ad52d7acc00fc1090d2edb0808bf61eeb0a"
    "152826f6261204f09f8da418a40185011220d9c0d5376d26f1931f7ad52d7acc00fc1090d2edb0808bf61eeb"
    "0a152826f62612310a221220d745b7757f5b4593eeab7820306c7bc64eb496a7410a0d07df7a34ffec4b97f1"
    "120962617272656c657965183a122e0a2401551220a2e1c40da1ae335d4dffe729eb4d5ca23b74b9e51fc535"
    "f4a804a261080c294d1204f09f90a11807581220d745b7757f5b4593eeab7820306c7bc64eb496a7410a0d07"
    "df7a34ffec4b97f112340a2401551220b474a99a2705e23cf905a484ec6d14ef58b56bbe62e9292783466ec3"
    "63b5072d120a666973686d6f6e67657218042801551220b474a99a2705e23cf905a484ec6d14ef58b56bbe62"
    "e9292783466ec363b5072d666973682b01551220a2e1c40da1ae335d4dffe729eb4d5ca23b74b9e51fc535f4"
    "a804a261080c294d6c6f62737465720100000028000000c800000000000000a2e1c40da1ae335d4dffe729eb"
    "4d5ca23b74b9e51fc535f4a804a261080c294d9401000000000000b474a99a2705e23cf905a484ec6d14ef58"
    "b56bbe62e9292783466ec363b5072d6b01000000000000d745b7757f5b4593eeab7820306c7bc64eb496a741"
    "0a0d07df7a34ffec4b97f11201000000000000d9c0d5376d26f1931f7ad52d7acc00fc1090d2edb0808bf61e"
    "eb0a152826f6268b00000000000000fb16f5083412ef1371d031ed4aa239903d84efdadf1ba3cd678e6475b1"
    "a232f83900000000000000"
)
SPEC_CARV2_ROOT = "QmfEoLyB5NndqeKieExd1rtJzTduQUPEV8TwAYcUiy3H5Z"
SPEC_CARV2_BLOCKS = [
    SPEC_CARV2_ROOT,
    "QmczfirA7VEH7YVvKPTPoU69XM3qY4DC39nnTsWd4K3SkM",
    "Qmcpz2FHJD7VAhg1fxFXdYJKePtkx1BsHuCrAgWVnaHMTE",
    "bafkreifuosuzujyf4i6psbneqtwg2fhplc2wxptc5euspa2gn3bwhnihfu",
    "bafkreifc4hca3inognou377hfhvu2xfchn2ltzi7yu27jkaeujqqqdbjju",
]


def carv2(
    payload: bytes,
    *,
    padding: int = 0,
    characteristics: bytes = bytes(16),
    offset: int | None = None,
    size: int | None = None,
    index: int | None = None,
    tail: bytes = b"",
) -> bytes:
    """A CARv2 around ``payload``: pragma, header, ``padding`` bytes, payload, ``tail`` (where
    an index would be). Offsets and sizes default to the true ones; any may be set to lie."""
    offset = CARV2_PREFIX_BYTES + padding if offset is None else offset
    size = len(payload) if size is None else size
    index = (CARV2_PREFIX_BYTES + padding + len(payload) if tail else 0) if index is None else index
    header = characteristics + b"".join(n.to_bytes(8, "little") for n in (offset, size, index))
    return CARV2_PRAGMA + header + b"\xee" * padding + payload + tail


def bit(*numbers: int) -> bytes:
    """A characteristics field with these bits set, bit 0 the left-most of the first byte."""
    field = bytearray(16)
    for number in numbers:
        field[number // 8] |= 0x80 >> (number % 8)
    return bytes(field)


def v1_blocks() -> tuple[bytes, list[Block]]:
    blocks = [Block(CID.from_block(data), data) for data in (b"one", b"two", b"three")]
    return car_with(blocks), blocks


def test_the_spec_fixture_written_by_go_car_is_read_and_its_index_left_unread() -> None:
    stream = io.BytesIO(SPEC_CARV2_BASIC)
    reader = CarReader(stream)
    assert reader.version == 2
    assert [str(root) for root in reader.roots] == [SPEC_CARV2_ROOT]
    assert [str(block.cid) for block in reader] == SPEC_CARV2_BLOCKS
    assert stream.tell() == 51 + 448  # the payload's end: the index after it is never read


@pytest.mark.parametrize("padding", [0, 1, 7, 100_000])
def test_a_wrapped_carv1_gives_the_same_roots_and_blocks(padding: int) -> None:
    v1, blocks = v1_blocks()
    stream = io.BytesIO(carv2(v1, padding=padding, tail=b"\x80\x08 not an index"))
    reader = CarReader(stream)
    assert (reader.version, reader.roots, list(reader)) == (2, [blocks[0].cid], blocks)
    assert stream.tell() == CARV2_PREFIX_BYTES + padding + len(v1)
    assert CarReader(io.BytesIO(v1)).version == 1


@pytest.mark.parametrize("bits", [(0,), (1,), (2,), (3,), (5,), (0, 1, 3, 5)])
def test_characteristics_the_spec_defines_and_import_does_not_need_are_taken(
    bits: tuple[int, ...],
) -> None:
    v1, blocks = v1_blocks()
    assert list(CarReader(io.BytesIO(carv2(v1, characteristics=bit(*bits))))) == blocks


V1, _ = v1_blocks()
END = CARV2_PREFIX_BYTES + len(V1)


@pytest.mark.parametrize(
    ("car", "message"),
    [
        (CARV2_PRAGMA, "truncated CARv2 header: 40 bytes due at byte 11, 0 there"),
        (carv2(V1)[:50], "truncated CARv2 header: 40 bytes due at byte 11, 39 there"),
        (carv2(V1, offset=50), "CARv2 data offset 50 is inside the pragma and header"),
        (carv2(V1, offset=0), "CARv2 data offset 0 is inside the pragma and header"),
        (
            carv2(V1, offset=END + 10, size=1),
            f"CARv2 data offset {END + 10} is beyond the end of the CAR at byte {END}",
        ),
        (
            carv2(V1, offset=(1 << 64) - 1),
            f"CARv2 data offset {(1 << 64) - 1} is beyond the end of the CAR at byte {END}",
        ),
        (carv2(V1, size=0), "CARv2 data size 0: the CAR has no CARv1 payload"),
        (
            carv2(V1, size=len(V1) + 1),
            f"CARv2 data size {len(V1) + 1} runs past the end of the CAR: the payload from "
            f"byte 51 would end at byte {END + 1}, the CAR ends at byte {END}",
        ),
        (
            carv2(V1, size=(1 << 64) - 1, index=0),
            f"CARv2 data size {(1 << 64) - 1} runs past the end of the CAR",
        ),
        (
            carv2(V1, size=len(V1) - 1),
            f"truncated CAR: 41 bytes due at byte {END - 41}, 40 there (the CARv2 data size ends "
            f"the payload at byte {END - 1})",
        ),
        (carv2(V1, index=END - 1), f"CARv2 index offset {END - 1} is inside the payload"),
        (carv2(V1, index=1), "CARv2 index offset 1 is inside the payload"),
        (carv2(carv2(V1)), "the CARv2 payload at byte 51 is not a CARv1 (its header's version"),
        (carv2(encode_varint(1) + b"\xa0"), "the CARv2 payload at byte 51 is not a CARv1"),
        (
            carv2(V1, characteristics=bit(6)),
            "unknown CARv2 characteristics bits set: 6 (the spec defines bits 0-5",
        ),
        (
            carv2(V1, characteristics=bit(0, 7, 64, 127)),
            "unknown CARv2 characteristics bits set: 7, 64, 127 (",
        ),
        (carv2(V1, characteristics=bit(4)), "bit 4 (zero-terminated-payload) is not supported"),
        (carv2(V1, characteristics=bit(2, 3)), "bits 2 (duplicates) and 3 (no-duplicates)"),
        (
            encode_varint(len(b"\xa2eroots\x80gversion\x02"))
            + b"\xa2eroots\x80gversion\x02"
            + carv2(V1)[11:],
            "a version 2 CAR header that is not the CARv2 pragma 0aa16776657273696f6e02",
        ),
        (
            encode_varint(len(b"\xa1gversion\x03")) + b"\xa1gversion\x03",
            "not a CARv1 or CARv2 header (version must be 1 or 2)",
        ),
    ],
    ids=[
        "pragma-alone",
        "truncated-header",
        "offset-in-header",
        "offset-zero",
        "offset-past-the-end",
        "offset-2^64",
        "size-zero",
        "size-one-past-the-end",
        "size-2^64",
        "size-cuts-a-section",
        "index-in-payload",
        "index-in-header",
        "payload-is-carv2",
        "payload-header-without-version",
        "unknown-bit",
        "unknown-bits",
        "zero-terminated",
        "duplicates-and-no-duplicates",
        "version-2-not-the-pragma",
        "version-3",
    ],
)
def test_malformed_carv2_is_named(car: bytes, message: str) -> None:
    with pytest.raises(CarError) as raised:
        list(CarReader(io.BytesIO(car)))
    assert message in str(raised.value)


def test_a_payload_ending_early_at_a_section_boundary_is_refused() -> None:
    """go-car would stop quietly here (the stream ends where a section could); the data size
    says more was due, so the CAR was cut."""
    v1, blocks = v1_blocks()
    cut = v1[: -(1 + len(blocks[-1].cid.binary) + len(blocks[-1].data))]
    reader = CarReader(io.BytesIO(carv2(cut, size=len(v1))))
    with pytest.raises(CarError, match="runs past the end of the CAR"):
        list(reader)


def test_every_carv1_bound_applies_to_the_payload_with_offsets_in_the_file() -> None:
    big = encode_varint(MAX_HEADER_BYTES + 1)
    with pytest.raises(CarError, match=f"more than {MAX_HEADER_BYTES}"):
        CarReader(io.BytesIO(carv2(big, size=MAX_HEADER_BYTES * 2)))
    header = encode_header([CID.from_block(b"x")] * (MAX_ROOTS + 1))
    with pytest.raises(CarError, match="1025 items, more than 1024"):
        CarReader(io.BytesIO(carv2(encode_varint(len(header)) + header)))
    section = HEADER + encode_varint(MAX_SECTION_BYTES + 1)
    with pytest.raises(CarError, match=f"section at byte {51 + len(HEADER)} of"):
        list(CarReader(io.BytesIO(carv2(section, size=MAX_SECTION_BYTES * 2))))
    good = Block(CID.from_block(b"good"), b"good")
    car = car_with([good, Block(good.cid, b"evil")])
    second = 7 + len(car) - (1 + len(good.cid.binary) + 4)
    with pytest.raises(CarError, match=f"section at byte {51 + second}: block does not match"):
        list(CarReader(io.BytesIO(carv2(car, padding=7))))
