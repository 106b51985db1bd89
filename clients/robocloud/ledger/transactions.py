"""Build, sign, send and confirm transactions with the robot's own key.

Robots sign their own transactions (the ledger never holds a key), so this module does what a
wallet does: estimate gas (which also surfaces a revert before anything is sent), take the
nonce and gas price from the node, sign an EIP-155 transaction for the node's chain id, send it
raw, and poll for the receipt. A mined transaction that reverted is replayed with ``eth_call``
on the state before its block so that the caller gets the contract's reason, not just status 0.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from eth_utils.address import to_checksum_address

from robocloud.identity import Identity
from robocloud.ledger.abi import ContractAbi
from robocloud.ledger.errors import RevertError, RpcError, TransactionTimeoutError
from robocloud.ledger.rpc import JsonRpcClient, as_revert

GAS_MARGIN = 1.25
"""Headroom over ``eth_estimateGas``: storage refunds and warm/cold slots vary between the
estimate and inclusion."""


def quantity(value: Any) -> int:
    """A JSON-RPC quantity (``0x``-hex) as an int."""
    return int(str(value), 16)


@dataclass(frozen=True)
class Receipt:
    """The parts of a transaction receipt that callers use."""

    tx_hash: str
    block_number: int
    block_hash: str
    status: int
    gas_used: int
    contract_address: str | None
    logs: list[dict[str, Any]] = field(repr=False)

    @classmethod
    def from_rpc(cls, raw: dict[str, Any]) -> Receipt:
        return cls(
            tx_hash=str(raw["transactionHash"]),
            block_number=quantity(raw["blockNumber"]),
            block_hash=str(raw["blockHash"]),
            status=quantity(raw["status"]),
            gas_used=quantity(raw["gasUsed"]),
            contract_address=(
                to_checksum_address(raw["contractAddress"]) if raw.get("contractAddress") else None
            ),
            logs=list(raw.get("logs") or []),
        )


class Transactor:
    """Sends the transactions of one identity to one node and waits for their receipts."""

    def __init__(
        self,
        rpc: JsonRpcClient,
        identity: Identity,
        *,
        contracts: list[ContractAbi] | None = None,
        receipt_timeout_s: float = 60.0,
        poll_interval_s: float = 0.05,
    ) -> None:
        self.rpc = rpc
        self.identity = identity
        self.contracts = contracts or []
        self.receipt_timeout_s = receipt_timeout_s
        self.poll_interval_s = poll_interval_s
        self._chain_id: int | None = None

    @property
    def chain_id(self) -> int:
        if self._chain_id is None:
            self._chain_id = quantity(self.rpc.request("eth_chainId", []))
        return self._chain_id

    def call_object(self, to: str | None, data: bytes, value: int = 0) -> dict[str, str]:
        call = {"from": self.identity.address, "data": "0x" + data.hex(), "value": hex(value)}
        if to is not None:
            call["to"] = to
        return call

    def estimate_gas(self, to: str | None, data: bytes, value: int = 0) -> int:
        """Gas for the call with headroom; raises ``RevertError`` if the call would revert."""
        try:
            estimate = quantity(
                self.rpc.request("eth_estimateGas", [self.call_object(to, data, value)])
            )
        except RpcError as exc:
            raise as_revert(exc, self.contracts) or exc from exc
        return int(estimate * GAS_MARGIN)

    def sign(self, to: str | None, data: bytes, *, gas: int, value: int = 0) -> bytes:
        """The raw signed transaction, with nonce and gas price from the node."""
        address = self.identity.address
        transaction: dict[str, Any] = {
            "chainId": self.chain_id,
            "nonce": quantity(self.rpc.request("eth_getTransactionCount", [address, "pending"])),
            "gas": gas,
            "gasPrice": quantity(self.rpc.request("eth_gasPrice", [])),
            "data": data,
            "value": value,
        }
        if to is not None:
            transaction["to"] = to_checksum_address(to)
        signed = self.identity.account.sign_transaction(transaction)
        return bytes(signed.raw_transaction)

    def send(
        self, to: str | None, data: bytes, *, value: int = 0, gas: int | None = None
    ) -> Receipt:
        """Sign, send and wait; raise ``RevertError`` (with the reason) if it reverts.

        Without ``gas`` the gas is estimated, so a call that would revert fails before
        anything is sent and costs nothing.
        """
        gas = gas if gas is not None else self.estimate_gas(to, data, value)
        raw = self.sign(to, data, gas=gas, value=value)
        tx_hash = str(self.rpc.request("eth_sendRawTransaction", ["0x" + raw.hex()]))
        receipt = self.wait_for_receipt(tx_hash)
        if receipt.status == 0:
            raise self._revert_of(to, data, value, receipt)
        return receipt

    def deploy(self, contract: ContractAbi, bytecode: str, *args: Any) -> Receipt:
        """Create a contract from its bytecode and constructor arguments."""
        data = bytes.fromhex(bytecode.removeprefix("0x")) + contract.encode_constructor(*args)
        return self.send(None, data)

    def wait_for_receipt(self, tx_hash: str) -> Receipt:
        deadline = time.monotonic() + self.receipt_timeout_s
        while True:
            raw = self.rpc.request("eth_getTransactionReceipt", [tx_hash])
            if raw is not None:
                return Receipt.from_rpc(raw)
            if time.monotonic() >= deadline:
                raise TransactionTimeoutError(tx_hash, self.receipt_timeout_s)
            time.sleep(self.poll_interval_s)

    def _revert_of(self, to: str | None, data: bytes, value: int, receipt: Receipt) -> RevertError:
        """Replay the reverted transaction as a call on the state its block started from."""
        block = hex(max(receipt.block_number - 1, 0))
        try:
            self.rpc.request("eth_call", [self.call_object(to, data, value), block])
        except RpcError as exc:
            revert = as_revert(exc, self.contracts)
            if revert is not None:
                return RevertError(revert.reason, tx_hash=receipt.tx_hash, data=revert.data)
        return RevertError(
            "execution reverted (the replay did not reproduce a reason; out of gas?)",
            tx_hash=receipt.tx_hash,
        )
