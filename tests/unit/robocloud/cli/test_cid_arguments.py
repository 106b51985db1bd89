"""CID text as the CLI accepts it, turned into the binary form that goes on chain."""

from __future__ import annotations

import base64
import hashlib
import json

import pytest
import typer

from robocloud.cli.ledger import cid_bytes, did_cid
from robocloud.identity import Identity
from tests.procs import SHARED_DATA

CHUNK_SHA256 = "7bdb75a98b03a7dead10d95621c79cfd626c7c17d2737d9319ab6af08debbfa3"
RAW_CID = "bafkreid33n22tcydu7pk2egzkyq4phh5mjwhyf6son6zggnlnlyi3257um"
V0_CID = "QmWmRj3dFDZdb6ABvbmKhEL6TmPbAfBZ1t5BxsEyJrcZhE"


def test_cidv1_raw_is_version_codec_and_the_file_digest() -> None:
    """The fixture's raw-leaf CID is the SHA-256 of its bytes (see shared/data/SOURCES.md)."""
    chunk = SHARED_DATA / "ipfs" / "files" / "chacha20_chunk-v0-seed_262144.bin"
    if chunk.is_file():
        assert hashlib.sha256(chunk.read_bytes()).hexdigest() == CHUNK_SHA256
    assert cid_bytes(RAW_CID) == bytes.fromhex("01551220" + CHUNK_SHA256)


def test_cidv0_is_its_multihash() -> None:
    binary = cid_bytes(V0_CID)
    assert len(binary) == 34
    assert binary[:2] == b"\x12\x20"


def test_base58_and_hex_forms_agree() -> None:
    binary = bytes.fromhex("01551220" + CHUNK_SHA256)
    assert cid_bytes("0x" + binary.hex()) == binary
    number = int.from_bytes(binary, "big")
    alphabet = "123456789ABCDEFGHJKLMNPQRSTUVWXYZabcdefghijkmnopqrstuvwxyz"
    digits = ""
    while number:
        number, digit = divmod(number, 58)
        digits = alphabet[digit] + digits
    assert cid_bytes("z" + digits) == binary


def test_vectors_file_cids_all_parse() -> None:
    vectors = SHARED_DATA / "ipfs" / "vectors.json"
    if not vectors.is_file():
        pytest.skip("shared IPFS vectors missing")
    strings = json.dumps(json.loads(vectors.read_text())).split('"')
    cids = [s for s in strings if s[:4] in {"bafy", "bafk"} or (s[:2] == "Qm" and len(s) == 46)]
    assert cids
    for cid in cids:
        binary = cid_bytes(cid)
        assert binary[0] == 0x01 or binary[:2] == b"\x12\x20", cid


@pytest.mark.parametrize("text", ["", "hello", "0xzz", "b!!!", "Qm" + "0" * 44, "0x02aa"])
def test_bad_cids_are_rejected(text: str) -> None:
    with pytest.raises(typer.BadParameter, match="is not a CID"):
        cid_bytes(text)


def test_did_cid_is_a_raw_cid_of_the_did() -> None:
    identity = Identity.generate()
    binary = did_cid(identity, 1337)
    expected = hashlib.sha256(f"did:pkh:eip155:1337:{identity.address}".encode()).digest()
    assert binary == bytes.fromhex("01551220") + expected
    text = "b" + base64.b32encode(binary).decode().lower().rstrip("=")
    assert cid_bytes(text) == binary
