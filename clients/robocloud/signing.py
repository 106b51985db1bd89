"""Request signing (ROBOCLOUD-REQUEST-V1), shared by robots and services.

A robot signs every state-changing request with its Ethereum key over a canonical string that
binds the method, path, query, time, a one-time nonce and the body's SHA-256. Services verify
with :func:`verify_request`; this module is the only implementation of the format so both
sides cannot drift apart. Host and scheme are deliberately not signed so proxies may rewrite
them.
"""

from __future__ import annotations

import hashlib
import re
import secrets
import time
from collections.abc import Mapping
from dataclasses import dataclass
from urllib.parse import parse_qsl, quote

from eth_account import Account
from eth_account.messages import encode_defunct
from eth_account.signers.local import LocalAccount
from eth_utils.address import to_checksum_address

from robocloud.errors import SignatureError

SCHEME = "ROBOCLOUD-REQUEST-V1"
MAX_CLOCK_SKEW_S = 300

HEADER_ADDRESS = "X-Robocloud-Address"
HEADER_TIMESTAMP = "X-Robocloud-Timestamp"
HEADER_NONCE = "X-Robocloud-Nonce"
HEADER_CONTENT_SHA256 = "X-Robocloud-Content-SHA256"
HEADER_SIGNATURE = "X-Robocloud-Signature"
SIGNATURE_HEADERS = (
    HEADER_ADDRESS,
    HEADER_TIMESTAMP,
    HEADER_NONCE,
    HEADER_CONTENT_SHA256,
    HEADER_SIGNATURE,
)

EMPTY_SHA256 = hashlib.sha256(b"").hexdigest()

_ADDRESS = re.compile(r"0x[0-9a-fA-F]{40}")
_TIMESTAMP = re.compile(r"[0-9]{1,12}")
_NONCE = re.compile(r"[A-Za-z0-9_-]{16,64}")
_SHA256 = re.compile(r"[0-9a-f]{64}")
_SIGNATURE = re.compile(r"0x[0-9a-fA-F]{130}")


def canonical_query(query: str) -> str:
    """Re-encode a raw query string canonically: pairs percent-encoded, sorted by key then value.

    Both sides decode the query as sent and encode it again, so that equivalent encodings
    (``%7E`` versus ``~``) sign identically.
    """
    pairs = parse_qsl(query, keep_blank_values=True)
    encoded = sorted((quote(k, safe=""), quote(v, safe="")) for k, v in pairs)
    return "&".join(f"{k}={v}" for k, v in encoded)


def canonical_request(
    method: str, path: str, query: str, timestamp: int, nonce: str, content_sha256: str
) -> str:
    """The exact text that is signed; ``path`` is percent-encoded as sent, without the query."""
    return "\n".join(
        [
            SCHEME,
            method.upper(),
            path,
            canonical_query(query),
            str(timestamp),
            nonce,
            content_sha256,
        ]
    )


def new_nonce() -> str:
    """A fresh 32-character nonce; 192 random bits make reuse by accident impossible."""
    return secrets.token_urlsafe(24)


def sign_request(
    account: LocalAccount,
    method: str,
    path: str,
    query: str = "",
    content_sha256: str = EMPTY_SHA256,
    *,
    timestamp: int | None = None,
    nonce: str | None = None,
) -> dict[str, str]:
    """The five signature headers for one request."""
    ts = int(time.time()) if timestamp is None else timestamp
    nonce = new_nonce() if nonce is None else nonce
    message = canonical_request(method, path, query, ts, nonce, content_sha256)
    signed = account.sign_message(encode_defunct(text=message))
    return {
        HEADER_ADDRESS: account.address,
        HEADER_TIMESTAMP: str(ts),
        HEADER_NONCE: nonce,
        HEADER_CONTENT_SHA256: content_sha256,
        HEADER_SIGNATURE: "0x" + bytes(signed.signature).hex(),
    }


@dataclass(frozen=True)
class VerifiedRequest:
    """What a valid signature proves: who signed, when, with which nonce, over which body."""

    address: str
    timestamp: int
    nonce: str
    content_sha256: str


def _header(headers: Mapping[str, str], name: str, pattern: re.Pattern[str]) -> str:
    value = headers.get(name)
    if value is None:
        raise SignatureError("missing_signature_header", f"header {name} is required", name)
    if not pattern.fullmatch(value):
        raise SignatureError("malformed_signature_header", f"header {name} is malformed", name)
    return value


def verify_request(
    method: str,
    path: str,
    query: str,
    headers: Mapping[str, str],
    *,
    now: float | None = None,
    max_skew_s: int = MAX_CLOCK_SKEW_S,
) -> VerifiedRequest:
    """Check the signature headers of a request; raise :class:`SignatureError` if any is wrong.

    ``headers`` must look names up case-insensitively (Starlette's and httpx's do). The nonce
    is only checked for form here; whether it was seen before is the caller's state.
    """
    address = _header(headers, HEADER_ADDRESS, _ADDRESS)
    timestamp = int(_header(headers, HEADER_TIMESTAMP, _TIMESTAMP))
    nonce = _header(headers, HEADER_NONCE, _NONCE)
    content_sha256 = _header(headers, HEADER_CONTENT_SHA256, _SHA256)
    signature = _header(headers, HEADER_SIGNATURE, _SIGNATURE)
    clock = time.time() if now is None else now
    if abs(clock - timestamp) > max_skew_s:
        raise SignatureError(
            "stale_timestamp",
            f"timestamp {timestamp} is more than {max_skew_s} s away from the server clock",
            HEADER_TIMESTAMP,
        )
    message = canonical_request(method, path, query, timestamp, nonce, content_sha256)
    try:
        recovered = Account.recover_message(
            encode_defunct(text=message), signature=bytes.fromhex(signature[2:])
        )
    except Exception as exc:  # eth-keys raises several types for unrecoverable signatures
        raise SignatureError(
            "invalid_signature", f"signature cannot be recovered: {exc}", HEADER_SIGNATURE
        ) from exc
    if recovered.lower() != address.lower():
        raise SignatureError(
            "invalid_signature",
            "signature does not match the request and the address header",
            HEADER_SIGNATURE,
        )
    return VerifiedRequest(to_checksum_address(address), timestamp, nonce, content_sha256)
