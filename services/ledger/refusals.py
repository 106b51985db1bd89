"""What the embedded chain refuses, with the JSON-RPC code Ethereum nodes use for each.

Kept apart from ``chain`` so that the validity rules (``validation``), the pending pool and
the chain itself raise the same exceptions without importing one another.
"""

from __future__ import annotations

from robocloud.ledger.abi import decode_revert


class ChainError(Exception):
    """A request the chain refuses; ``code`` is the JSON-RPC error code nodes use for it."""

    code = -32000

    def __init__(self, message: str, data: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.data = data


class InvalidParams(ChainError):
    """The request itself is malformed (not decodable, wrong types)."""

    code = -32602


class Reverted(ChainError):
    """The EVM reverted; ``data`` is the revert payload and the message carries its reason.

    An empty payload (``revert()`` without a reason) is plain ``execution reverted``, as geth
    and anvil answer it, so that clients classify it as a revert and not as another error.
    """

    code = 3

    def __init__(self, payload: bytes) -> None:
        message = (
            f"execution reverted: {decode_revert(payload)}" if payload else "execution reverted"
        )
        super().__init__(message, "0x" + payload.hex())
        self.payload = payload
