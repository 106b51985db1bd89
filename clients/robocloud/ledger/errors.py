"""Errors of the ledger client, under the SDK's ``RobocloudError``.

A robot mostly needs to tell three things apart: the node refused the request (``RpcError``),
the contract refused the call (``RevertError``, with the contract's own reason), and the
transaction was sent but not mined in time (``TransactionTimeoutError``, it may still land).
A node that cannot be reached raises the SDK's ``TransportError``; one whose answer is not
JSON-RPC, ``InvalidAnswerError``; the ledger service's REST errors are ``ApiError``s.
"""

from __future__ import annotations

from typing import Any

from robocloud.errors import FormatError, InvalidAnswerError, RobocloudError, shown_text


class LedgerError(RobocloudError):
    """Base of every ledger client error."""


class RpcError(LedgerError):
    """The node answered a JSON-RPC error object (bad transaction, wrong chain, nonce too low).

    The JSON-RPC counterpart of ``ApiError``: ``code``, ``message`` and ``data`` are the error
    object's, ``status`` the HTTP status it came with (usually 200) and ``request_id`` the
    ledger service's ``X-Request-Id`` when there is one.
    """

    def __init__(
        self,
        method: str,
        code: int,
        message: str,
        data: Any = None,
        *,
        status: int = 200,
        request_id: str | None = None,
    ) -> None:
        super().__init__(f"{method}: {shown_text(message)} (JSON-RPC error {code})")
        self.method = method
        self.code = code
        self.message = message
        self.data = data
        self.status = status
        self.request_id = request_id


class RevertError(LedgerError):
    """The contract reverted; ``reason`` is its decoded reason (``Registry: ...``).

    ``tx_hash`` is set when a mined transaction reverted, and is None when the revert was found
    before sending (by ``eth_estimateGas`` or ``eth_call``), in which case nothing was sent.
    """

    def __init__(self, reason: str, *, tx_hash: str | None = None, data: bytes = b"") -> None:
        where = f" in transaction {tx_hash}" if tx_hash else ""
        super().__init__(f"reverted{where}: {shown_text(reason)}")
        self.reason = reason
        self.tx_hash = tx_hash
        self.data = data


class TransactionTimeoutError(LedgerError):
    """No receipt within the timeout; the transaction may still be mined later."""

    def __init__(self, tx_hash: str, timeout_s: float) -> None:
        super().__init__(f"no receipt for {tx_hash} after {timeout_s:g} s")
        self.tx_hash = tx_hash
        self.timeout_s = timeout_s


class ContractsUnavailableError(LedgerError, InvalidAnswerError):
    """The ledger service did not say where the contracts are deployed."""


class AddressError(LedgerError, FormatError):
    """Text that is not an Ethereum address (``0x`` and 40 hex digits, checksum if mixed case)."""


class DeploymentMismatchError(LedgerError, InvalidAnswerError):
    """The node serves another chain, or the ledger service names another Registry, than the
    deployment the robot means (``ROBOCLOUD_EXPECTED_DEPLOYMENT``): nothing was signed for it."""


class FeeLimitError(LedgerError):
    """A transaction would take more gas, or cost more per gas, than this robot pays.

    The gas and the gas price come from the node, which the robot does not trust: a lying
    node could otherwise have it sign away its balance in fees. Nothing was signed.
    """


class TransactionMismatchError(LedgerError, InvalidAnswerError):
    """The node answered, for the transaction the robot sent, a hash or a receipt that is not
    that transaction's: another's, or a malformed one.

    The robot's own transaction was sent and may still be mined: ``tx_hash`` is its real hash
    (keccak-256 of the signed bytes), to look up on a node the robot trusts.
    """

    def __init__(self, message: str, tx_hash: str) -> None:
        super().__init__(message)
        self.tx_hash = tx_hash
