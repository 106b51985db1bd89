"""The REST reads: query parameters checked, index rows turned into JSON documents.

CIDs go on chain in binary; here they come back both as their text form (``b...``) and as
hex, so that a robot can compare either with what it holds. Role ids come back by name.
"""

from __future__ import annotations

from typing import Any

from eth_utils.address import is_address, to_checksum_address

from robocloud.cid import CID, CIDError, parse_cid
from robocloud.ledger.models import Role
from services.ledger.node import Ledger

ROLE_NAMES = {role.id: role.value for role in Role}
MAX_LIMIT = 1000


class InvalidAddress(ValueError):
    """A parameter that should hold an Ethereum address does not."""

    def __init__(self, name: str, value: str) -> None:
        super().__init__(f"{name} {value!r} is not an Ethereum address")
        self.name = name
        self.value = value


class InvalidLimit(ValueError):
    def __init__(self, value: int) -> None:
        super().__init__(f"limit must be between 1 and {MAX_LIMIT}")
        self.value = value


class RobotNotFound(LookupError):
    def __init__(self, address: str) -> None:
        super().__init__(f"robot {address} is not registered on this ledger")
        self.address = address


def address_param(value: str, name: str) -> str:
    """A checksummed address, or :class:`InvalidAddress` naming the parameter."""
    if not is_address(value):
        raise InvalidAddress(name, value)
    return str(to_checksum_address(value))


def limit_param(value: int) -> int:
    if not 1 <= value <= MAX_LIMIT:
        raise InvalidLimit(value)
    return value


def cid_view(binary: bytes) -> dict[str, str | None]:
    """A binary CID as text and hex; text is None for bytes that are not a CID."""
    try:
        text: str | None = str(CID.from_bytes(binary))
    except (CIDError, ValueError):
        text = None
    return {"cid": text, "hex": "0x" + binary.hex()}


def robot(ledger: Ledger, address: str) -> dict[str, Any]:
    """A registered robot, or one whose registration awaits a registrar (``status``)."""
    checked = address_param(address, "address")
    found = ledger.index.robot(checked)
    if found is not None:
        return {
            "address": checked,
            "did": f"did:pkh:eip155:{ledger.chain_id}:{checked}",
            "status": "registered",
            "metadata": cid_view(found["metadata_cid"]),
            "registered_at": found["registered_at"],
            "registered_block": found["registered_block"],
            "active": found["active"] and not found["suspended"],
            "deactivated": not found["active"],
            "suspended": found["suspended"],
            "roles": sorted(ROLE_NAMES.get(role, "0x" + role.hex()) for role in found["roles"]),
        }
    pending = ledger.index.pending(checked, 1)
    if not pending:
        raise RobotNotFound(checked)
    return _pending_view(ledger, pending[0])


def pending_registrations(ledger: Ledger, limit: int) -> dict[str, Any]:
    """Registrations awaiting the admin or a registrar, oldest first."""
    rows = ledger.index.pending(None, limit_param(limit))
    return {"pending": [_pending_view(ledger, row) for row in rows]}


def _pending_view(ledger: Ledger, row: dict[str, Any]) -> dict[str, Any]:
    return {
        "address": row["address"],
        "did": f"did:pkh:eip155:{ledger.chain_id}:{row['address']}",
        "status": "pending",
        "metadata": cid_view(row["metadata_cid"]),
        "registered_at": row["requested_at"],
        "registered_block": row["requested_block"],
        "active": False,
        "deactivated": False,
        "suspended": False,
        "roles": [],
    }


def advertisements(
    ledger: Ledger,
    cid: str | None,
    advertiser: str | None,
    since: int,
    limit: int,
    after_log_index: int | None = None,
) -> dict[str, Any]:
    rows = ledger.index.advertisements(
        parse_cid(cid, "cid").binary if cid else None,
        address_param(advertiser, "advertiser") if advertiser else None,
        since,
        limit_param(limit),
        after_log_index,
    )
    return {
        "advertisements": [
            {
                **cid_view(row["cid"]),
                "advertiser": row["advertiser"],
                "description": cid_view(row["description_cid"]) if row["description_cid"] else None,
                "first": row["first"],
                "timestamp": row["timestamp"],
                "block_number": row["block_number"],
                "log_index": row["log_index"],
                "tx": "0x" + row["tx_hash"].hex(),
            }
            for row in rows
        ]
    }


def anchors(ledger: Ledger, node: str | None, epoch: int | None, limit: int) -> dict[str, Any]:
    rows = ledger.index.anchors(
        address_param(node, "node") if node else None, epoch, limit_param(limit)
    )
    return {
        "anchors": [
            {
                "node": row["node"],
                "epoch": row["epoch"],
                "root": "0x" + row["root"].hex(),
                "record_count": row["record_count"],
                "timestamp": row["timestamp"],
                "block_number": row["block_number"],
                "tx": "0x" + row["tx_hash"].hex(),
                "chain_id": ledger.chain_id,
                "contract": ledger.deployment.anchor_log,
            }
            for row in rows
        ]
    }
