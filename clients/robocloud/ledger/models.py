"""What the ledger client returns: plain, typed records of on-chain state and events."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Any

from eth_utils.crypto import keccak


class Role(Enum):
    """Registry roles; the on-chain id is keccak-256 of ``robocloud.role.<name>``."""

    STORAGE_NODE = "storage_node"
    REVIEWER = "reviewer"
    AGGREGATOR = "aggregator"
    REGISTRAR = "registrar"

    @property
    def id(self) -> bytes:
        return keccak(text=f"robocloud.role.{self.value}")


class RegistrationMode(Enum):
    """How the Registry admits robots; the values are the contract's enum."""

    OPEN = 0
    APPROVED = 1


@dataclass(frozen=True)
class Robot:
    """A Registry record; an unknown address reads as ``registered=False``."""

    address: str
    metadata_cid: bytes
    registered_at: int
    registered: bool
    active: bool
    suspended: bool

    @property
    def is_active(self) -> bool:
        """What the contracts check: registered, not deactivated, not suspended."""
        return self.registered and self.active and not self.suspended


@dataclass(frozen=True)
class RegisteredRobot:
    """A robot as the ledger service's index reports it (``GET /v1/robots/{address}``).

    ``metadata_cid`` is the text form (None when the bytes on chain are not a CID);
    ``active`` already accounts for suspension, as the service reports it. ``status`` is
    ``registered``, or ``pending`` for a robot that asked to register and awaits a registrar
    (Approved mode): such a robot is not active, holds no role, and its ``registered_at`` is
    when it asked.
    """

    address: str
    metadata_cid: str | None
    metadata_hex: str
    registered_at: int
    active: bool
    suspended: bool
    roles: tuple[str, ...]
    status: str = "registered"

    @property
    def pending(self) -> bool:
        return self.status == "pending"

    @classmethod
    def from_service(cls, body: Any) -> RegisteredRobot:
        """Parse the service's document; ``TypeError``/``KeyError`` name what is malformed."""
        if not isinstance(body, dict) or not isinstance(body.get("metadata"), dict):
            raise TypeError("expected an object with a metadata object")
        metadata = body["metadata"]
        robot = cls(
            address=body["address"],
            metadata_cid=metadata.get("cid"),
            metadata_hex=metadata["hex"],
            registered_at=body["registered_at"],
            active=body["active"],
            suspended=body["suspended"],
            roles=tuple(body["roles"]),
            status=body.get("status", "registered"),
        )
        robot._check_types()
        return robot

    def _check_types(self) -> None:
        expected: dict[str, type | tuple[type, ...]] = {
            "address": str,
            "metadata_cid": (str, type(None)),
            "metadata_hex": str,
            "registered_at": int,
            "active": bool,
            "suspended": bool,
            "status": str,
        }
        for name, kind in expected.items():
            if not isinstance(getattr(self, name), kind):
                raise TypeError(f"{name} has the wrong type")
        if not all(isinstance(role, str) for role in self.roles):
            raise TypeError("roles must be strings")
        if self.status not in ("registered", "pending"):
            raise ValueError(f"status must be registered or pending, not {self.status[:40]!r}")
        if self.pending and (self.active or self.roles):
            raise ValueError("a pending robot can be neither active nor hold roles")


@dataclass(frozen=True)
class Advertisement:
    """The Registry's summary of a CID: who advertised it first, when, and how often."""

    cid: bytes
    first_advertiser: str
    first_timestamp: int
    first_block: int
    count: int
    description_cid: bytes


@dataclass(frozen=True)
class Advertised:
    """One ``Advertised`` event: a robot announced that it holds ``cid``."""

    cid: bytes
    advertiser: str
    description_cid: bytes
    first: bool
    timestamp: int
    block_number: int
    tx_hash: str


@dataclass(frozen=True)
class IndexedAdvertisement:
    """An ``Advertised`` event as the ledger service's index lists it (``GET /v1/advertisements``).

    ``cid`` and ``description`` are CID text, None where the bytes on chain are not a CID (or,
    for ``description``, empty); ``(block_number, log_index)`` orders events.
    """

    cid: str | None
    advertiser: str
    description: str | None
    first: bool
    timestamp: int
    block_number: int
    log_index: int
    tx_hash: str


@dataclass(frozen=True)
class Anchor:
    """A storage node's Template Merkle Tree root for one epoch."""

    node: str
    epoch: int
    root: bytes
    record_count: int
    timestamp: int
    block_number: int
    tx_hash: str | None = None
