"""ROBOCLOUD-REQUEST-V1: the canonical string, a pinned vector, and every tampering rejected."""

from __future__ import annotations

import hashlib

import pytest
from eth_account import Account
from eth_account.messages import encode_defunct

from robocloud.errors import SignatureError
from robocloud.identity import Identity
from robocloud.signing import (
    HEADER_ADDRESS,
    HEADER_CONTENT_SHA256,
    HEADER_NONCE,
    HEADER_SIGNATURE,
    HEADER_TIMESTAMP,
    canonical_query,
    canonical_request,
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
SIGNATURE = (
    "0xa2df3d56de1c79bb3a054c1a8bfdd019adc7b9e6bfd49d6e3102804b073dcdb1"
    "390e80beee0175cf57d23961b89f393e0755bf6ca787e3d27574beccb8a3c5fc1c"
)


@pytest.fixture
def headers() -> dict[str, str]:
    account = Identity.from_key(KEY).account
    return sign_request(
        account, "POST", "/v1/whoami", "b=2&a=1", BODY_SHA256, timestamp=TS, nonce=NONCE
    )


def test_canonical_string_is_exactly_the_documented_lines() -> None:
    text = canonical_request("post", "/v1/whoami", "b=2&a=1", TS, NONCE, BODY_SHA256)
    assert text == (
        "ROBOCLOUD-REQUEST-V1\nPOST\n/v1/whoami\na=1&b=2\n1700000000\n"
        f"0123456789abcdef\n{BODY_SHA256}"
    )
    assert hashlib.sha256(BODY).hexdigest() == BODY_SHA256


def test_fixed_key_vector_pins_the_signature_bytes(headers: dict[str, str]) -> None:
    assert headers == {
        HEADER_ADDRESS: ADDRESS,
        HEADER_TIMESTAMP: "1700000000",
        HEADER_NONCE: NONCE,
        HEADER_CONTENT_SHA256: BODY_SHA256,
        HEADER_SIGNATURE: SIGNATURE,
    }


def test_signature_is_plain_eth_account_eip191_over_the_canonical_string() -> None:
    text = canonical_request("POST", "/v1/whoami", "a=1&b=2", TS, NONCE, BODY_SHA256)
    signed = Account.sign_message(encode_defunct(text=text), KEY)
    assert "0x" + bytes(signed.signature).hex() == SIGNATURE


def test_valid_request_verifies_to_the_checksummed_address(headers: dict[str, str]) -> None:
    verified = verify_request("POST", "/v1/whoami", "a=1&b=2", headers, now=TS + 10)
    assert verified.address == ADDRESS
    assert (verified.nonce, verified.timestamp) == (NONCE, TS)
    assert verified.content_sha256 == BODY_SHA256


@pytest.mark.parametrize(
    ("query", "canonical"),
    [
        ("", ""),
        ("b=2&a=1", "a=1&b=2"),
        ("a=2&a=1", "a=1&a=2"),
        ("z=%7E&a=b+c&a=%20a&k=", "a=%20a&a=b%20c&k=&z=~"),
        ("path=%2Fx%2Fy", "path=%2Fx%2Fy"),
        ("q=caf%C3%A9", "q=caf%C3%A9"),
    ],
)
def test_query_is_decoded_then_encoded_canonically(query: str, canonical: str) -> None:
    assert canonical_query(query) == canonical


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
        verify_request(method, path, query, headers, now=now)
    assert caught.value.code == "invalid_signature"


def test_changed_timestamp_header_is_rejected(headers: dict[str, str]) -> None:
    headers = {**headers, HEADER_TIMESTAMP: str(TS + 1)}
    with pytest.raises(SignatureError) as caught:
        verify_request("POST", "/v1/whoami", "a=1&b=2", headers, now=TS)
    assert caught.value.code == "invalid_signature"


@pytest.mark.parametrize("skew", [-301, 301, 10_000])
def test_timestamp_outside_the_window_is_rejected(headers: dict[str, str], skew: int) -> None:
    with pytest.raises(SignatureError) as caught:
        verify_request("POST", "/v1/whoami", "a=1&b=2", headers, now=TS + skew)
    assert caught.value.code == "stale_timestamp"
    assert caught.value.header == HEADER_TIMESTAMP


def test_other_address_header_is_rejected(headers: dict[str, str]) -> None:
    headers = {**headers, HEADER_ADDRESS: Identity.generate().address}
    with pytest.raises(SignatureError) as caught:
        verify_request("POST", "/v1/whoami", "a=1&b=2", headers, now=TS)
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
        verify_request("POST", "/v1/whoami", "a=1&b=2", headers, now=TS)
    assert caught.value.code == "malformed_signature_header"
    assert caught.value.header == header


@pytest.mark.parametrize("header", [HEADER_ADDRESS, HEADER_SIGNATURE, HEADER_NONCE])
def test_missing_header_is_named(headers: dict[str, str], header: str) -> None:
    del headers[header]
    with pytest.raises(SignatureError) as caught:
        verify_request("POST", "/v1/whoami", "a=1&b=2", headers, now=TS)
    assert caught.value.code == "missing_signature_header"
    assert caught.value.header == header


def test_unrecoverable_signature_is_rejected(headers: dict[str, str]) -> None:
    headers = {**headers, HEADER_SIGNATURE: "0x" + "00" * 65}
    with pytest.raises(SignatureError) as caught:
        verify_request("POST", "/v1/whoami", "a=1&b=2", headers, now=TS)
    assert caught.value.code == "invalid_signature"
