"""Contract event logs as a JSON-RPC node sends them (in a receipt, to ``eth_getLogs``).

Tests of what the SDK and the storage node's anchorer take from a node build the node's
answers here, so that a lie is one field changed in an event that is otherwise the one the
contract emits, and every test encodes that event the same way.
"""

from __future__ import annotations

from typing import Any

from eth_abi.abi import encode

from robocloud.ledger import Anchor, ContractAbi

ANCHORED = ContractAbi.load("AnchorLog").event_topic("Anchored")


def anchored_log(anchor_log: str, anchor: Anchor) -> dict[str, Any]:
    """The ``Anchored`` event the AnchorLog at ``anchor_log`` emits for ``anchor``: what
    ``Ledger`` reads back as ``anchor``, its block and transaction included."""
    if anchor.tx_hash is None:
        raise ValueError("a log names its transaction: give the anchor a tx_hash")
    data = encode(
        ["bytes32", "uint64", "uint64"], [anchor.root, anchor.record_count, anchor.timestamp]
    )
    return {
        "address": anchor_log,
        "topics": [
            "0x" + ANCHORED.hex(),
            "0x" + "00" * 12 + anchor.node[2:].lower(),
            "0x" + anchor.epoch.to_bytes(32, "big").hex(),
        ],
        "data": "0x" + data.hex(),
        "blockNumber": hex(anchor.block_number),
        "transactionHash": anchor.tx_hash,
        "logIndex": "0x0",
    }
