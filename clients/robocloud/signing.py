"""Request signing (ROBOCLOUD-REQUEST-V2), shared by robots and services.

A robot signs every state-changing request with its Ethereum key over a canonical string that
binds the audience (the one service of one deployment the request is meant for), the method,
path, query, time, a one-time nonce and the body's SHA-256. Services verify with
:func:`verify_request`; this module is the only implementation of the format so both sides
cannot drift apart. Host and scheme are deliberately not signed so proxies may rewrite them;
the audience is what stops a service, or anyone who sees a request, from replaying it to
another service or another deployment.
"""

from __future__ import annotations

import hashlib
import re
import secrets
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qsl, quote, unquote

from robocloud import bounded_json
from robocloud.errors import FormatError, SignatureError

if TYPE_CHECKING:
    from eth_account.signers.local import LocalAccount

SCHEME = "ROBOCLOUD-REQUEST-V2"
MAX_CLOCK_SKEW_S = 300

HEADER_ADDRESS = "X-Robocloud-Address"
HEADER_TIMESTAMP = "X-Robocloud-Timestamp"
HEADER_NONCE = "X-Robocloud-Nonce"
HEADER_CONTENT_SHA256 = "X-Robocloud-Content-SHA256"
HEADER_AUDIENCE = "X-Robocloud-Audience"
HEADER_SIGNATURE = "X-Robocloud-Signature"
SIGNATURE_HEADERS = (
    HEADER_ADDRESS,
    HEADER_TIMESTAMP,
    HEADER_NONCE,
    HEADER_CONTENT_SHA256,
    HEADER_AUDIENCE,
    HEADER_SIGNATURE,
)

EMPTY_SHA256 = hashlib.sha256(b"").hexdigest()

SECP256K1_N = 0xFFFFFFFFFFFFFFFFFFFFFFFFFFFFFFFEBAAEDCE6AF48A03BBFD25E8CD0364141
"""The order of secp256k1; for each valid ``(r, s)`` the pair ``(r, n - s)`` verifies too."""

LOCAL_DEPLOYMENT = "local"
"""The deployment id of services that run without a ledger (``ROBOCLOUD_AUTH=signed``)."""

_ADDRESS = re.compile(r"0x[0-9a-fA-F]{40}")
_TIMESTAMP = re.compile(r"[0-9]{1,12}")
_NONCE = re.compile(r"[A-Za-z0-9_-]{16,64}")
_SHA256 = re.compile(r"[0-9a-f]{64}")
_SIGNATURE = re.compile(r"0x[0-9a-fA-F]{130}")
SERVICE_NAME = re.compile(r"[a-z][a-z0-9_-]{0,62}")
"""A service's name in its audience: ``cas``, ..., or the name an operator gives a replica."""
DEPLOYMENT_ID = re.compile(r"[A-Za-z0-9._:-]{1,128}")
"""Any deployment id: ``<chain id>:<registry>`` from a ledger, or an operator's own."""
CHAIN_DEPLOYMENT_ID = re.compile(r"[0-9]{1,20}:0x[0-9a-f]{40}")
"""A deployment id learned from a ledger: chain id and lowercase Registry address."""
_AUDIENCE = re.compile(
    rf"(?P<service>{SERVICE_NAME.pattern})@(?P<deployment>{DEPLOYMENT_ID.pattern})"
)


class AudienceError(FormatError):
    """Text that is not an audience ``<service>@<deployment>`` (or a deployment id)."""


@dataclass(frozen=True)
class Audience:
    """Who a signed request is for: one service (``service``) of one deployment."""

    service: str
    deployment: str

    def __str__(self) -> str:
        return f"{self.service}@{self.deployment}"

    def describe(self) -> dict[str, str]:
        """The document ``GET /v1/audience`` serves."""
        return {"audience": str(self), "service": self.service, "deployment": self.deployment}


def chain_deployment_id(chain_id: int, registry: str) -> str:
    """The deployment id of a robocloud on a chain: ``<chain id>:<Registry address, lowercase>``."""
    deployment = f"{chain_id}:{registry.lower()}"
    if not CHAIN_DEPLOYMENT_ID.fullmatch(deployment):
        raise AudienceError(f"chain {chain_id} and registry {registry!r} make no deployment id")
    return deployment


def parse_audience(text: str) -> Audience:
    """``<service>@<deployment>`` as an :class:`Audience`; :class:`AudienceError` otherwise."""
    match = _AUDIENCE.fullmatch(text)
    if match is None:
        raise AudienceError(f"{text[:200]!r} is not an audience <service>@<deployment>")
    return Audience(match["service"], match["deployment"])


def audience_from_answer(document: bytes, expected_deployment: str | None = None) -> Audience:
    """The audience in a service's ``GET /v1/audience`` answer, checked for consistency and,
    when the robot names the deployment it means, for belonging to it.

    Anyone can read a service's audience and claim it: a server of another deployment that
    answers with this one's would be handed signatures it could replay here. Only the robot
    knows which deployment it meant to talk to, so only its own setting can refuse the claim.
    """
    answer: Any = bounded_json.loads(document)
    if not isinstance(answer, dict) or not all(
        isinstance(answer.get(key), str) for key in ("audience", "service", "deployment")
    ):
        raise AudienceError("an audience answer holds the strings audience, service, deployment")
    audience = parse_audience(answer["audience"])
    if (audience.service, audience.deployment) != (answer["service"], answer["deployment"]):
        raise AudienceError(f"audience {audience} disagrees with its service and deployment")
    if expected_deployment is not None and audience.deployment != expected_deployment:
        raise AudienceError(
            f"the service claims deployment {audience.deployment[:200]!r}, "
            f"but this robot expects {expected_deployment!r}: it signs nothing for it"
        )
    return audience


def canonical_query(query: str) -> str:
    """Re-encode a raw query string canonically: pairs percent-encoded, sorted by key then value.

    Both sides decode the query as sent and encode it again, so that equivalent encodings
    (``%7E`` versus ``~``) sign identically.
    """
    pairs = [
        (quote(k, safe=""), quote(v, safe="")) for k, v in parse_qsl(query, keep_blank_values=True)
    ]
    _check_repeated_keys_sorted(pairs)
    return "&".join(f"{k}={v}" for k, v in sorted(pairs))


def _check_repeated_keys_sorted(pairs: list[tuple[str, str]]) -> None:
    """Refuse a key repeated with its values out of sorted order.

    The signature covers the values sorted, while a service reading one value takes the last
    sent: ``?pin=false&pin=true`` sent as ``?pin=true&pin=false`` would keep the signature
    and change the meaning. Sent in sorted order, what is read is what was signed.
    """
    values: dict[str, list[str]] = {}
    for key, value in pairs:
        values.setdefault(key, []).append(value)
    for key, sent in values.items():
        if sent != sorted(sent):
            raise SignatureError(
                "ambiguous_query",
                f"the query key {unquote(key)[:100]!r} repeats with its values out of sorted "
                "order; the signature covers them sorted, so send them sorted",
            )


def canonical_request(
    audience: str,
    method: str,
    path: str,
    query: str,
    timestamp: int,
    nonce: str,
    content_sha256: str,
) -> str:
    """The exact text that is signed; ``path`` is percent-encoded as sent, without the query."""
    return "\n".join(
        [
            SCHEME,
            audience,
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
    audience: str,
    method: str,
    path: str,
    query: str = "",
    content_sha256: str = EMPTY_SHA256,
    *,
    timestamp: int | None = None,
    nonce: str | None = None,
) -> dict[str, str]:
    """The six signature headers for one request to the service whose audience is given."""
    from eth_account.messages import encode_defunct  # on first use (robocloud.identity._account)

    parse_audience(audience)
    ts = int(time.time()) if timestamp is None else timestamp
    nonce = new_nonce() if nonce is None else nonce
    message = canonical_request(audience, method, path, query, ts, nonce, content_sha256)
    signed = account.sign_message(encode_defunct(text=message))
    return {
        HEADER_ADDRESS: account.address,
        HEADER_TIMESTAMP: str(ts),
        HEADER_NONCE: nonce,
        HEADER_CONTENT_SHA256: content_sha256,
        HEADER_AUDIENCE: audience,
        HEADER_SIGNATURE: "0x" + bytes(signed.signature).hex(),
    }


@dataclass(frozen=True)
class VerifiedRequest:
    """What a valid signature proves: who signed, when, with which nonce, over which body."""

    address: str
    timestamp: int
    nonce: str
    content_sha256: str
    audience: str


class WrongAudienceError(SignatureError):
    """A request signed for another service or another deployment."""

    def __init__(self, received: str, expected: str) -> None:
        super().__init__(
            "wrong_audience",
            f"header {HEADER_AUDIENCE} is {received!r}, but this service is {expected!r}: "
            "the request was signed for another service or deployment",
            HEADER_AUDIENCE,
        )
        self.received = received
        self.expected = expected


def _header(headers: Mapping[str, str], name: str, pattern: re.Pattern[str]) -> str:
    value = headers.get(name)
    if value is None:
        raise SignatureError("missing_signature_header", f"header {name} is required", name)
    if not pattern.fullmatch(value):
        raise SignatureError("malformed_signature_header", f"header {name} is malformed", name)
    return value


def _audience_header(headers: Mapping[str, str]) -> str:
    if headers.get(HEADER_AUDIENCE) is None:
        raise SignatureError(
            "unsupported_signature_version",
            f"header {HEADER_AUDIENCE} is missing: a ROBOCLOUD-REQUEST-V1 signature (or none) "
            f"was sent, and only {SCHEME} is accepted; it signs the audience "
            "(GET /v1/audience names it)",
            HEADER_AUDIENCE,
        )
    return _header(headers, HEADER_AUDIENCE, _AUDIENCE)


def _canonical_signature(signature: bytes) -> None:
    """Refuse the two other encodings of a valid signature, so that each request has one.

    ``(r, n - s)`` with the flipped recovery id verifies as well as ``(r, s)`` (malleability);
    EIP-2 keeps only the low ``s``. eth-account also recovers with ``v`` 0 or 1; the format
    fixes 27 or 28, as ``sign_message`` writes them.
    """
    v = signature[64]
    if v not in (27, 28):
        raise SignatureError(
            "non_canonical_signature",
            f"signature v is {v}; it must be 27 or 28",
            HEADER_SIGNATURE,
        )
    if int.from_bytes(signature[32:64], "big") > SECP256K1_N // 2:
        raise SignatureError(
            "non_canonical_signature",
            "signature s is above secp256k1n/2 (a malleable high-s signature); sign with low s",
            HEADER_SIGNATURE,
        )


def verify_request(
    method: str,
    path: str,
    query: str,
    headers: Mapping[str, str],
    *,
    audience: str,
    now: float | None = None,
    max_skew_s: int = MAX_CLOCK_SKEW_S,
) -> VerifiedRequest:
    """Check the signature headers of a request; raise :class:`SignatureError` if any is wrong.

    ``audience`` is the verifying service's own; a request signed for any other is refused
    with :class:`WrongAudienceError` before the (costlier) signature recovery. ``headers``
    must look names up case-insensitively (Starlette's and httpx's do). The nonce is only
    checked for form here; whether it was seen before is the caller's state.
    """
    address = _header(headers, HEADER_ADDRESS, _ADDRESS)
    timestamp = int(_header(headers, HEADER_TIMESTAMP, _TIMESTAMP))
    nonce = _header(headers, HEADER_NONCE, _NONCE)
    content_sha256 = _header(headers, HEADER_CONTENT_SHA256, _SHA256)
    signature = bytes.fromhex(_header(headers, HEADER_SIGNATURE, _SIGNATURE)[2:])
    signed_for = _audience_header(headers)
    if signed_for != audience:
        raise WrongAudienceError(signed_for, audience)
    clock = time.time() if now is None else now
    if abs(clock - timestamp) > max_skew_s:
        raise SignatureError(
            "stale_timestamp",
            f"timestamp {timestamp} is more than {max_skew_s} s away from the server clock",
            HEADER_TIMESTAMP,
        )
    _canonical_signature(signature)
    message = canonical_request(audience, method, path, query, timestamp, nonce, content_sha256)
    from eth_account import Account  # on first use (robocloud.identity._account)
    from eth_account.messages import encode_defunct

    try:
        recovered = Account.recover_message(encode_defunct(text=message), signature=signature)
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
    return VerifiedRequest(recovered, timestamp, nonce, content_sha256, audience)
