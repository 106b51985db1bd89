"""The storage node's own identity: the key that signs its anchors, and its Registry standing.

The key is generated at the first start and kept only as an encrypted keystore (Web3 Secret
Storage) at ``keys/node.json`` in the data directory, as the ledger keeps its operator keys.
The passphrase comes from ``ROBOCLOUD_STORAGE_NODE_PASSPHRASE``; without it a random one is
generated once into ``node.secret`` (mode 0600), so that a development node needs no
configuration and the key never sits on disk in the clear.

AnchorLog accepts roots only from an active robot holding the ``storage_node`` role: the node
registers itself (funded by the development faucet when it has no ether), and the ledger's
admin grants the role, either the ledger itself at start (``ROBOCLOUD_LEDGER_GRANT_ROLES``,
the default under ``make up`` and compose) or an operator with ``robocloud admin grant``.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

from robocloud.cid import CID
from robocloud.identity import Identity
from robocloud.ledger import Ledger
from robocloud.ledger.models import Role
from services.common.keystores import KeyPassphrase, key_passphrase, service_key

log = logging.getLogger("robocloud.storage.identity")

SECRET_FILE = "node.secret"
KEYSTORE = Path("keys") / "node.json"


def passphrase(data_dir: Path, configured: str | None) -> KeyPassphrase:
    """The configured passphrase, else the one generated into ``node.secret``."""
    return key_passphrase(configured, data_dir / SECRET_FILE)


def load_or_create(data_dir: Path, configured_passphrase: str | None) -> Identity:
    """The node's key from its keystore, generated and saved on the first start."""
    data_dir.mkdir(parents=True, exist_ok=True)
    return service_key(data_dir / KEYSTORE, passphrase(data_dir, configured_passphrase))


class Standing(Enum):
    """Where the node stands on the Registry, in the order it gets there."""

    UNREGISTERED = "unregistered"
    PENDING = "pending"
    REGISTERED = "registered"
    ANCHORING = "anchoring"
    """Active and holding the storage-node role: AnchorLog takes its roots."""


@dataclass(frozen=True)
class NodeIdentity:
    identity: Identity
    _registering: threading.Lock = field(
        default_factory=threading.Lock, init=False, repr=False, compare=False
    )
    """Held by ``ensure_registered``: the anchorer and the dataset publisher both register the
    node before their first transaction, and both read it unregistered and registered it (one
    reverting, "already registered", the first dataset left unpublished)."""

    @property
    def address(self) -> str:
        return self.identity.address

    def metadata_cid(self, chain_id: int) -> bytes:
        """What the node registers with: the raw CID of its DID, as robots do by default."""
        return CID.from_block(self.identity.did(chain_id).encode()).binary

    def standing(self, ledger: Ledger) -> Standing:
        """Read from the chain (``eth_call``), never from an index."""
        if ledger.has_role(self.address, Role.STORAGE_NODE):
            return Standing.ANCHORING
        if ledger.robot(self.address).registered:
            return Standing.REGISTERED
        if ledger.is_pending(self.address):
            return Standing.PENDING
        return Standing.UNREGISTERED

    def ensure_registered(self, ledger: Ledger) -> Standing:
        """Register the node if it is not (asking the faucet for gas first when unfunded).

        The role itself is the admin's to grant; this only gets the node to where a grant
        can find it. Raises what the ledger raises, for the caller to retry later.
        """
        with self._registering:
            standing = self.standing(ledger)
            if standing is not Standing.UNREGISTERED:
                return standing
            if ledger.balance() == 0 and ledger.service is not None:
                ledger.faucet()
            receipt = ledger.register(self.metadata_cid(ledger.chain_id))
            log.info("registered", extra={"address": self.address, "tx": receipt.tx_hash})
            return self.standing(ledger)
