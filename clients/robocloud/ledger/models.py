"""What the ledger client returns: plain, typed records of on-chain state and events."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from eth_utils.crypto import keccak


class Role(Enum):
    """Registry roles; the on-chain id is keccak-256 of ``robocloud.role.<name>``."""

    STORAGE_NODE = "storage_node"
    REVIEWER = "reviewer"
    AGGREGATOR = "aggregator"

    @property
    def id(self) -> bytes:
        return keccak(text=f"robocloud.role.{self.value}")


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
class Anchor:
    """A storage node's Template Merkle Tree root for one epoch."""

    node: str
    epoch: int
    root: bytes
    record_count: int
    timestamp: int
    block_number: int
    tx_hash: str | None = None
