"""CIDs: text and binary forms, verification, and clear errors for bad input."""

from __future__ import annotations

import pytest

from robocloud.cid import (
    CID,
    DAG_PB,
    MAX_CID_TEXT,
    RAW,
    CIDError,
    VarintError,
    b58decode,
    b58encode,
    decode_varint,
    encode_varint,
)

HELLO = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"
EMPTY_DIR_V0 = "QmUNLLsPACCz1vLxQVkXqqLX5R1X345qqfHbsf67hvA3Nn"


def test_hello_world_is_the_documented_raw_cid() -> None:
    cid = CID.from_block(b"Hello world")
    assert str(cid) == HELLO
    assert (cid.version, cid.codec) == (1, RAW)
    assert CID.decode(HELLO) == cid


def test_binary_form_round_trips() -> None:
    cid = CID.decode(HELLO)
    assert cid.binary[:2] == b"\x01\x55"
    assert CID.from_bytes(cid.binary) == cid
    assert CID.read(cid.binary + b"tail", 0) == (cid, len(cid.binary))


def test_v0_is_base58_dag_pb_and_converts_to_v1() -> None:
    cid = CID.decode(EMPTY_DIR_V0)
    assert (cid.version, cid.codec) == (0, DAG_PB)
    assert str(cid) == EMPTY_DIR_V0
    assert cid.binary == cid.multihash
    assert str(cid.to_v1()) == "bafybeiczsscdsbs7ffqz55asqdf3smv6klcw3gofszvwlyarci47bgf354"
    cid.verify(bytes.fromhex("0a020801"))


@pytest.mark.parametrize(
    "text",
    [
        "f01551220" + CID.decode(HELLO).digest.hex(),
        "B" + HELLO[1:].upper(),
        "z" + b58encode(CID.decode(HELLO).binary),
        "b" + HELLO[1:20].upper() + HELLO[20:],
        "F01551220" + CID.decode(HELLO).digest.hex().upper(),
    ],
    ids=["base16", "base32-upper", "base58btc", "base32-mixed-case", "base16-upper-digits"],
)
def test_other_multibases_are_accepted_as_input(text: str) -> None:
    assert str(CID.decode(text)) == HELLO


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("", "unsupported multibase"),
        ("hello", "unsupported multibase"),
        ("bafkrei", "Incorrect padding"),
        ("b" + "a" * 10, ""),
        ("bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq0", ""),
        ("Qm" + "0" * 44, "base58btc"),
        ("f015512" + "10" + "00" * 16, "32 bytes"),
        ("f01551320" + "00" * 32, "unsupported multihash"),
        ("f02551220" + "00" * 32, "version"),
        ("f01 55 12 20" + "00" * 32, "outside multibase 'f'"),
        ("F01551220" + "00" * 31 + "\t00", "outside multibase 'F'"),
        (HELLO[:-2] + "==", "outside multibase 'b'"),
        ("b" + HELLO[1:-1] + "\n", "outside multibase 'b'"),
    ],
)
def test_invalid_cid_is_rejected_quoting_it(text: str, reason: str) -> None:
    with pytest.raises(CIDError) as caught:
        CID.decode(text)
    assert repr(text) in str(caught.value)
    assert reason in str(caught.value)


def test_v0_in_base32_is_not_a_cid_text_form() -> None:
    v0 = CID.decode(EMPTY_DIR_V0)
    with pytest.raises(CIDError, match="base58btc"):
        CID.decode("b" + __import__("base64").b32encode(v0.binary).decode().lower().rstrip("="))


def test_verify_rejects_other_bytes() -> None:
    with pytest.raises(CIDError, match=HELLO):
        CID.decode(HELLO).verify(b"Hello world!")


def test_identity_cid_verifies_inline_data() -> None:
    cid = CID(1, RAW, b"\x00\x05hello")
    cid.verify(b"hello")
    with pytest.raises(CIDError):
        cid.verify(b"hellO")
    assert CID.decode(str(cid)) == cid


@pytest.mark.parametrize("value", [0, 1, 127, 128, 300, 2**32, 2**63 - 1])
def test_varints_round_trip(value: int) -> None:
    assert decode_varint(encode_varint(value)) == (value, len(encode_varint(value)))


@pytest.mark.parametrize(
    ("encoded", "message"),
    [
        (b"\xff" * 10 + b"\x01", "varint at byte 0 is longer than 9 bytes"),
        (b"\xff" * 9 + b"\x01", "varint at byte 0 is longer than 9 bytes"),
        (b"\x81\x00", "varint at byte 0 is not minimally encoded"),
        (b"\x80", "varint at byte 0 is truncated"),
        (b"", "varint at byte 0 is truncated"),
    ],
    ids=["11-bytes", "10-bytes", "not-minimal", "truncated", "empty"],
)
def test_varints_follow_the_multiformats_rules(encoded: bytes, message: str) -> None:
    with pytest.raises(VarintError, match=message):
        decode_varint(encoded)


def test_a_binary_cid_with_a_bad_varint_is_named_with_its_offset() -> None:
    good = CID.decode(HELLO).binary
    with pytest.raises(CIDError, match="invalid binary CID at byte 3: varint at byte 4 is not"):
        CID.read(b"pad" + b"\x01\xd5\x00" + good[2:], 3)
    with pytest.raises(CIDError, match="at byte 0: varint at byte 0 is longer than 9 bytes"):
        CID.from_bytes(b"\xff" * 11)
    with pytest.raises(CIDError, match="a 32-byte digest, 31 bytes left"):
        CID.from_bytes(good[:-1])


def test_overlong_text_is_refused_unparsed() -> None:
    text = "z" + "2" * MAX_CID_TEXT
    with pytest.raises(CIDError, match=f"more than {MAX_CID_TEXT}"):
        CID.decode(text)


def test_base58_keeps_leading_zeros() -> None:
    assert b58decode(b58encode(b"\0\0abc")) == b"\0\0abc"
