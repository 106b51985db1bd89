"""ROBOCLOUD-REQUEST-V2: the canonical string, a pinned vector, and every tampering rejected."""

from __future__ import annotations

import hashlib
import json

import pytest
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.asymmetric.utils import Prehashed, encode_dss_signature
from eth_account import Account
from eth_account.messages import encode_defunct
from eth_utils.crypto import keccak

from robocloud.bounded_json import JsonDepthError
from robocloud.errors import SignatureError
from robocloud.identity import Identity
from robocloud.signing import (
    HEADER_ADDRESS,
    HEADER_AUDIENCE,
    HEADER_CONTENT_SHA256,
    HEADER_NONCE,
    HEADER_SIGNATURE,
    HEADER_TIMESTAMP,
    SECP256K1_N,
    Audience,
    AudienceError,
    WrongAudienceError,
    audience_from_answer,
    canonical_query,
    canonical_request,
    chain_deployment_id,
    parse_audience,
    sign_request,
    verify_request,
)

# The private key from eth-account's documentation: a public, fixed test key.
KEY = "0x4c0883a69102937d6231471b5dbb6204fe5129617082792ae468d01a3f362318"
ADDRESS = "0x2c7536E3605D9C16a7a3D7b1898e529396a65c23"
BODY = b'{"challenge":"hi"}'
BODY_SHA256 = "2129992947e4503c176bd6fdeba3f4f29d87e9e74aa512299821535888c62a8f"
TS = 1700000000
NONCE = "0123456789abcdef"
AUDIENCE = "storage@1337:0x5fbdb2315678afecb367f032d93f642f64180aa3"
SIGNATURE = (
    "0x82778f944341a7e9ed56a04c5001714178d3a598e36b4a77e94a1dbb09e8e503"
    "3a1c7968ad6c1199a7323d69ee4625adfe0bb4dcf92761eea4da56b3a5dbd0541c"
)
CANONICAL = (
    "ROBOCLOUD-REQUEST-V2\n"
    f"{AUDIENCE}\n"
    "POST\n/v1/whoami\na=1&b=2\n1700000000\n0123456789abcdef\n"
    f"{BODY_SHA256}"
)


@pytest.fixture
def headers() -> dict[str, str]:
    account = Identity.from_key(KEY).account
    return sign_request(
        account, AUDIENCE, "POST", "/v1/whoami", "b=2&a=1", BODY_SHA256, timestamp=TS, nonce=NONCE
    )


def verify(headers: dict[str, str], *, audience: str = AUDIENCE, now: int = TS) -> object:
    return verify_request("POST", "/v1/whoami", "a=1&b=2", headers, audience=audience, now=now)


def test_canonical_string_is_exactly_the_documented_lines() -> None:
    text = canonical_request(AUDIENCE, "post", "/v1/whoami", "b=2&a=1", TS, NONCE, BODY_SHA256)
    assert text == CANONICAL
    assert hashlib.sha256(BODY).hexdigest() == BODY_SHA256


def test_fixed_key_vector_pins_the_signature_bytes(headers: dict[str, str]) -> None:
    assert headers == {
        HEADER_ADDRESS: ADDRESS,
        HEADER_TIMESTAMP: "1700000000",
        HEADER_NONCE: NONCE,
        HEADER_CONTENT_SHA256: BODY_SHA256,
        HEADER_AUDIENCE: AUDIENCE,
        HEADER_SIGNATURE: SIGNATURE,
    }


def test_signature_is_plain_eth_account_eip191_over_the_canonical_string() -> None:
    signed = Account.sign_message(encode_defunct(text=CANONICAL), KEY)
    assert "0x" + bytes(signed.signature).hex() == SIGNATURE


def test_vector_verifies_as_raw_ecdsa_over_the_eip191_digest() -> None:
    """Independent of eth-account: keccak-256 of the EIP-191 prefix and text, plain ECDSA."""
    message = CANONICAL.encode()
    digest = keccak(b"\x19Ethereum Signed Message:\n" + str(len(message)).encode() + message)
    signature = bytes.fromhex(SIGNATURE[2:])
    r, s = int.from_bytes(signature[:32], "big"), int.from_bytes(signature[32:64], "big")
    public = ec.derive_private_key(int(KEY, 16), ec.SECP256K1()).public_key()
    public.verify(encode_dss_signature(r, s), digest, ec.ECDSA(Prehashed(hashes.SHA256())))
    assert s <= SECP256K1_N // 2
    assert signature[64] in (27, 28)


def test_valid_request_verifies_to_the_checksummed_address(headers: dict[str, str]) -> None:
    verified = verify_request(
        "POST", "/v1/whoami", "a=1&b=2", headers, audience=AUDIENCE, now=TS + 10
    )
    assert verified.address == ADDRESS
    assert (verified.nonce, verified.timestamp) == (NONCE, TS)
    assert verified.content_sha256 == BODY_SHA256
    assert verified.audience == AUDIENCE


@pytest.mark.parametrize(
    "other",
    [
        "cas@1337:0x5fbdb2315678afecb367f032d93f642f64180aa3",
        "ledger@1337:0x5fbdb2315678afecb367f032d93f642f64180aa3",
        "storage@1337:0x0000000000000000000000000000000000000001",
        "storage@31337:0x5fbdb2315678afecb367f032d93f642f64180aa3",
        "storage@local",
        "storage-eu@1337:0x5fbdb2315678afecb367f032d93f642f64180aa3",
    ],
    ids=["other-service", "ledger", "other-registry", "other-chain", "local", "replica"],
)
def test_signature_for_another_audience_is_refused_naming_both(
    headers: dict[str, str], other: str
) -> None:
    """The service checks its own audience: a request signed for storage is good nowhere else."""
    with pytest.raises(WrongAudienceError) as caught:
        verify(headers, audience=other)
    assert caught.value.code == "wrong_audience"
    assert caught.value.header == HEADER_AUDIENCE
    assert (caught.value.received, caught.value.expected) == (AUDIENCE, other)
    assert other in caught.value.message


def test_audience_header_changed_to_the_verifiers_fails_the_signature(
    headers: dict[str, str],
) -> None:
    """Rewriting the header to the target's audience does not help: the audience is signed."""
    target = "cas@1337:0x5fbdb2315678afecb367f032d93f642f64180aa3"
    with pytest.raises(SignatureError) as caught:
        verify({**headers, HEADER_AUDIENCE: target}, audience=target)
    assert caught.value.code == "invalid_signature"


def test_v1_signature_is_refused_naming_v2() -> None:
    """A V1 request (five headers, no audience, V1 canonical string) is told to use V2."""
    v1_text = "\n".join(
        ["ROBOCLOUD-REQUEST-V1", "POST", "/v1/whoami", "a=1&b=2", str(TS), NONCE, BODY_SHA256]
    )
    signed = Account.sign_message(encode_defunct(text=v1_text), KEY)
    v1_headers = {
        HEADER_ADDRESS: ADDRESS,
        HEADER_TIMESTAMP: str(TS),
        HEADER_NONCE: NONCE,
        HEADER_CONTENT_SHA256: BODY_SHA256,
        HEADER_SIGNATURE: "0x" + bytes(signed.signature).hex(),
    }
    with pytest.raises(SignatureError) as caught:
        verify(v1_headers)
    assert caught.value.code == "unsupported_signature_version"
    assert caught.value.header == HEADER_AUDIENCE
    assert "ROBOCLOUD-REQUEST-V2" in caught.value.message


def test_high_s_twin_of_a_valid_signature_is_refused(headers: dict[str, str]) -> None:
    """``(r, n - s)`` with the other recovery id recovers the same address: it must not pass."""
    signature = bytes.fromhex(headers[HEADER_SIGNATURE][2:])
    s = int.from_bytes(signature[32:64], "big")
    twin = signature[:32] + (SECP256K1_N - s).to_bytes(32, "big") + bytes([55 - signature[64]])
    twin_hex = "0x" + twin.hex()
    assert Account.recover_message(encode_defunct(text=CANONICAL), signature=twin) == ADDRESS
    with pytest.raises(SignatureError) as caught:
        verify({**headers, HEADER_SIGNATURE: twin_hex})
    assert caught.value.code == "non_canonical_signature"
    assert caught.value.header == HEADER_SIGNATURE
    assert "high-s" in caught.value.message


@pytest.mark.parametrize("v_offset", [-27, -26, 2, 8])
def test_v_other_than_27_or_28_is_refused(headers: dict[str, str], v_offset: int) -> None:
    """eth-account would recover v = 0 and 1 too; the format allows only 27 and 28."""
    signature = bytearray.fromhex(headers[HEADER_SIGNATURE][2:])
    signature[64] += v_offset
    with pytest.raises(SignatureError) as caught:
        verify({**headers, HEADER_SIGNATURE: "0x" + signature.hex()})
    assert caught.value.code == "non_canonical_signature"
    assert f"v is {signature[64]}" in caught.value.message


def test_signing_for_a_malformed_audience_is_refused() -> None:
    account = Identity.from_key(KEY).account
    with pytest.raises(AudienceError):
        sign_request(account, "storage", "POST", "/v1/whoami")


@pytest.mark.parametrize(
    "value",
    [
        "storage",
        "@local",
        "Storage@local",
        "storage@",
        "storage@local\n",
        "a@b@c",
        "s@" + "x" * 200,
    ],
)
def test_malformed_audience_header_is_named(headers: dict[str, str], value: str) -> None:
    with pytest.raises(SignatureError) as caught:
        verify({**headers, HEADER_AUDIENCE: value})
    assert caught.value.code == "malformed_signature_header"
    assert caught.value.header == HEADER_AUDIENCE


def test_audience_parts_and_the_chain_deployment_id() -> None:
    registry = "0x5FbDB2315678afecb367f032d93F642f64180aa3"
    deployment = chain_deployment_id(1337, registry)
    assert deployment == "1337:0x5fbdb2315678afecb367f032d93f642f64180aa3"
    assert parse_audience(f"storage@{deployment}") == Audience("storage", deployment)
    assert str(Audience("cas", "local")) == "cas@local"
    with pytest.raises(AudienceError):
        chain_deployment_id(1337, "not-an-address")


def test_audience_answer_is_parsed_and_checked_for_consistency() -> None:
    good = {"audience": "cas@local", "service": "cas", "deployment": "local"}
    assert audience_from_answer(json.dumps(good).encode()) == Audience("cas", "local")
    for bad in (
        {**good, "service": "ledger"},
        {**good, "deployment": "1:0x" + "0" * 40},
        {**good, "audience": "cas"},
        {"audience": "cas@local"},
        ["cas@local"],
        {**good, "service": 5},
    ):
        with pytest.raises(AudienceError):
            audience_from_answer(json.dumps(bad).encode())
    with pytest.raises(JsonDepthError):
        audience_from_answer(b"[" * 100_000 + b"]" * 100_000)


@pytest.mark.parametrize(
    ("query", "canonical"),
    [
        ("", ""),
        ("b=2&a=1", "a=1&b=2"),
        ("b=1&a=2&b=3", "a=2&b=1&b=3"),
        ("z=%7E&a=%20a&a=b+c&k=", "a=%20a&a=b%20c&k=&z=~"),
        ("path=%2Fx%2Fy", "path=%2Fx%2Fy"),
        ("q=caf%C3%A9", "q=caf%C3%A9"),
    ],
)
def test_query_is_decoded_then_encoded_canonically(query: str, canonical: str) -> None:
    assert canonical_query(query) == canonical


@pytest.mark.parametrize("query", ["pin=true&pin=false", "arg=b&x=1&arg=a", "a=b+c&a=%20a"])
def test_a_key_repeated_out_of_sorted_order_is_refused(query: str) -> None:
    """Signed sorted but read last-wins: the order sent could change what a service reads."""
    with pytest.raises(SignatureError) as refused:
        canonical_query(query)
    assert refused.value.code == "ambiguous_query"


@pytest.mark.parametrize(
    ("method", "path", "query", "content_sha256", "now"),
    [
        ("PUT", "/v1/whoami", "a=1&b=2", BODY_SHA256, TS),
        ("POST", "/v1/whoami/", "a=1&b=2", BODY_SHA256, TS),
        ("POST", "/v1/whoami", "a=1&b=3", BODY_SHA256, TS),
        ("POST", "/v1/whoami", "a=1", BODY_SHA256, TS),
        ("POST", "/v1/whoami", "a=1&b=2", hashlib.sha256(b"other").hexdigest(), TS),
    ],
    ids=["method", "path", "query-value", "query-missing", "body"],
)
def test_any_change_to_the_request_is_rejected(
    headers: dict[str, str], method: str, path: str, query: str, content_sha256: str, now: int
) -> None:
    headers = {**headers, HEADER_CONTENT_SHA256: content_sha256}
    with pytest.raises(SignatureError) as caught:
        verify_request(method, path, query, headers, audience=AUDIENCE, now=now)
    assert caught.value.code == "invalid_signature"


def test_changed_timestamp_header_is_rejected(headers: dict[str, str]) -> None:
    headers = {**headers, HEADER_TIMESTAMP: str(TS + 1)}
    with pytest.raises(SignatureError) as caught:
        verify(headers)
    assert caught.value.code == "invalid_signature"


@pytest.mark.parametrize("skew", [-301, 301, 10_000])
def test_timestamp_outside_the_window_is_rejected(headers: dict[str, str], skew: int) -> None:
    with pytest.raises(SignatureError) as caught:
        verify(headers, now=TS + skew)
    assert caught.value.code == "stale_timestamp"
    assert caught.value.header == HEADER_TIMESTAMP


def test_other_address_header_is_rejected(headers: dict[str, str]) -> None:
    headers = {**headers, HEADER_ADDRESS: Identity.generate().address}
    with pytest.raises(SignatureError) as caught:
        verify(headers)
    assert caught.value.code == "invalid_signature"


@pytest.mark.parametrize(
    ("header", "value"),
    [
        (HEADER_ADDRESS, "0x1234"),
        (HEADER_ADDRESS, "2c7536E3605D9C16a7a3D7b1898e529396a65c23"),
        (HEADER_TIMESTAMP, "17e8"),
        (HEADER_TIMESTAMP, "-1"),
        (HEADER_NONCE, "short"),
        (HEADER_NONCE, "has spaces in the nonce!"),
        (HEADER_NONCE, "x" * 65),
        (HEADER_CONTENT_SHA256, BODY_SHA256.upper()),
        (HEADER_SIGNATURE, "0x" + "zz" * 65),
        (HEADER_SIGNATURE, SIGNATURE[:-2]),
    ],
)
def test_malformed_header_is_named(headers: dict[str, str], header: str, value: str) -> None:
    headers = {**headers, header: value}
    with pytest.raises(SignatureError) as caught:
        verify(headers)
    assert caught.value.code == "malformed_signature_header"
    assert caught.value.header == header


@pytest.mark.parametrize("header", [HEADER_ADDRESS, HEADER_SIGNATURE, HEADER_NONCE])
def test_missing_header_is_named(headers: dict[str, str], header: str) -> None:
    del headers[header]
    with pytest.raises(SignatureError) as caught:
        verify(headers)
    assert caught.value.code == "missing_signature_header"
    assert caught.value.header == header


@pytest.mark.parametrize("r_s", ["00" * 64, "ff" * 32 + "01" * 32, "00" * 32 + "01" * 32])
def test_unrecoverable_signature_is_rejected(headers: dict[str, str], r_s: str) -> None:
    headers = {**headers, HEADER_SIGNATURE: "0x" + r_s + "1b"}
    with pytest.raises(SignatureError) as caught:
        verify(headers)
    assert caught.value.code == "invalid_signature"
