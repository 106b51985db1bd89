"""py-evm's blocks, transactions, receipts and logs in Ethereum JSON-RPC form.

JSON-RPC quantities are ``0x``-hex without leading zeros, data is ``0x``-hex of its bytes,
addresses are lower-case hex (checksums are the client's business, as with geth). These are
the shapes web3.py, ethers and the SDK parse, so they follow the execution-apis spec field by
field rather than eth-tester's Python-side representation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import rlp
from eth.abc import BlockAPI, BlockHeaderAPI, ReceiptAPI, SignedTransactionAPI
from eth.vm.forks.prague.constants import SET_CODE_TRANSACTION_TYPE
from eth_utils.address import to_checksum_address
from eth_utils.crypto import keccak

from services.ledger.chain import gas_used_by, receipt_status

ZERO_ADDRESS = b"\x00" * 20


def quantity(value: int) -> str:
    return hex(value)


def data(value: bytes) -> str:
    return "0x" + value.hex()


def address(value: bytes) -> str:
    return "0x" + value.hex()


@dataclass(frozen=True)
class LogEntry:
    """One event log and where it was emitted: what the event index stores."""

    block_number: int
    block_hash: bytes
    tx_hash: bytes
    tx_index: int
    log_index: int
    address: bytes
    topics: tuple[bytes, ...]
    data: bytes

    def to_rpc(self) -> dict[str, Any]:
        return {
            "address": address(self.address),
            "topics": [data(topic) for topic in self.topics],
            "data": data(self.data),
            "blockNumber": quantity(self.block_number),
            "blockHash": data(self.block_hash),
            "transactionHash": data(self.tx_hash),
            "transactionIndex": quantity(self.tx_index),
            "logIndex": quantity(self.log_index),
            "removed": False,
        }

    @classmethod
    def from_rpc(cls, log: dict[str, Any]) -> LogEntry:
        """Parse a node's JSON-RPC log object (external-node mode)."""
        return cls(
            block_number=int(str(log["blockNumber"]), 16),
            block_hash=_bytes(log["blockHash"]),
            tx_hash=_bytes(log["transactionHash"]),
            tx_index=int(str(log["transactionIndex"]), 16),
            log_index=int(str(log["logIndex"]), 16),
            address=_bytes(log["address"]),
            topics=tuple(_bytes(topic) for topic in log.get("topics", [])),
            data=_bytes(log.get("data", "0x")),
        )


def _bytes(value: object) -> bytes:
    return bytes.fromhex(str(value).removeprefix("0x"))


def block_logs(block: BlockAPI, receipts: tuple[ReceiptAPI, ...]) -> list[LogEntry]:
    """Every log of a block, numbered block-wide as ``logIndex`` is."""
    entries: list[LogEntry] = []
    for tx_index, (transaction, receipt) in enumerate(
        zip(block.transactions, receipts, strict=True)
    ):
        for log in receipt.logs:
            entries.append(
                LogEntry(
                    block_number=block.number,
                    block_hash=block.hash,
                    tx_hash=transaction.hash,
                    tx_index=tx_index,
                    log_index=len(entries),
                    address=log.address,
                    topics=tuple(topic.to_bytes(32, "big") for topic in log.topics),
                    data=log.data,
                )
            )
    return entries


def transaction_fields(tx: SignedTransactionAPI) -> dict[str, Any]:
    """The signed fields of a transaction, by its type."""
    fields: dict[str, Any] = {
        "hash": data(tx.hash),
        "type": quantity(tx.type_id or 0),
        "nonce": quantity(tx.nonce),
        "from": address(tx.sender),
        "to": address(tx.to) if tx.to else None,
        "value": quantity(tx.value),
        "gas": quantity(tx.gas),
        "input": data(tx.data),
        "r": quantity(tx.r),
        "s": quantity(tx.s),
    }
    if tx.type_id is None:
        fields["gasPrice"] = quantity(tx.gas_price)
        legacy: Any = tx  # legacy transactions carry v; the typed API has only y_parity
        fields["v"] = quantity(legacy.v)
        if tx.chain_id is not None:
            fields["chainId"] = quantity(tx.chain_id)
        return fields
    assert tx.chain_id is not None, "typed transactions (EIP-2718) always carry a chain id"
    fields["chainId"] = quantity(tx.chain_id)
    fields["v"] = quantity(tx.y_parity)
    fields["yParity"] = quantity(tx.y_parity)
    fields["accessList"] = [
        {
            "address": address(entry[0]),
            "storageKeys": [data(k.to_bytes(32, "big")) for k in entry[1]],
        }
        for entry in tx.access_list
    ]
    if tx.type_id == 1:
        fields["gasPrice"] = quantity(tx.gas_price)
    else:
        fields["maxFeePerGas"] = quantity(tx.max_fee_per_gas)
        fields["maxPriorityFeePerGas"] = quantity(tx.max_priority_fee_per_gas)
    if tx.type_id == SET_CODE_TRANSACTION_TYPE:
        fields["authorizationList"] = [
            {
                "chainId": quantity(auth.chain_id),
                "address": address(auth.address),
                "nonce": quantity(auth.nonce),
                "yParity": quantity(auth.y_parity),
                "r": quantity(auth.r),
                "s": quantity(auth.s),
            }
            for auth in tx.authorization_list
        ]
    return fields


def base_fee(header: BlockHeaderAPI) -> int:
    """The header's base fee; every block of a London-or-later chain has one."""
    return int(header.base_fee_per_gas or 0)


def effective_gas_price(tx: SignedTransactionAPI, base_fee: int) -> int:
    if tx.type_id in (None, 1):
        return int(tx.gas_price)
    return int(min(tx.max_fee_per_gas, base_fee + tx.max_priority_fee_per_gas))


def transaction(block: BlockAPI, index: int, tx: SignedTransactionAPI) -> dict[str, Any]:
    """``tx``, the block's ``index``-th transaction, as ``eth_getTransactionByHash``."""
    fields = transaction_fields(tx)
    fields |= {
        "blockHash": data(block.hash),
        "blockNumber": quantity(block.number),
        "transactionIndex": quantity(index),
    }
    if tx.type_id not in (None, 1):
        fields["gasPrice"] = quantity(effective_gas_price(tx, base_fee(block.header)))
    return fields


def pending_transaction(tx: SignedTransactionAPI, next_base_fee: int) -> dict[str, Any]:
    """A transaction in the pool, as geth and anvil show one: in no block yet, its gas price
    what it would pay in the next block."""
    fields = transaction_fields(tx)
    fields |= {"blockHash": None, "blockNumber": None, "transactionIndex": None}
    if tx.type_id not in (None, 1):
        fields["gasPrice"] = quantity(effective_gas_price(tx, next_base_fee))
    return fields


def block(value: BlockAPI, full_transactions: bool) -> dict[str, Any]:
    header = value.header
    transactions: list[Any] = (
        [transaction(value, i, tx) for i, tx in enumerate(value.transactions)]
        if full_transactions
        else [data(tx.hash) for tx in value.transactions]
    )
    body: dict[str, Any] = {
        "number": quantity(header.block_number),
        "hash": data(header.hash),
        "parentHash": data(header.parent_hash),
        "nonce": data(header.nonce),
        "sha3Uncles": data(header.uncles_hash),
        "logsBloom": data(header.bloom.to_bytes(256, "big")),
        "transactionsRoot": data(header.transaction_root),
        "stateRoot": data(header.state_root),
        "receiptsRoot": data(header.receipt_root),
        "miner": address(header.coinbase),
        "difficulty": quantity(header.difficulty),
        "totalDifficulty": quantity(header.difficulty),
        "extraData": data(header.extra_data),
        "size": quantity(len(rlp.encode(value))),
        "gasLimit": quantity(header.gas_limit),
        "gasUsed": quantity(header.gas_used),
        "timestamp": quantity(header.timestamp),
        "mixHash": data(header.mix_hash),
        "baseFeePerGas": quantity(base_fee(header)),
        "transactions": transactions,
        "uncles": [],
    }
    for name, key in (
        ("withdrawals_root", "withdrawalsRoot"),
        ("parent_beacon_block_root", "parentBeaconBlockRoot"),
        ("requests_hash", "requestsHash"),
    ):
        value_bytes = getattr(header, name, None)
        if value_bytes is not None:
            body[key] = data(value_bytes)
    for name, key in (("blob_gas_used", "blobGasUsed"), ("excess_blob_gas", "excessBlobGas")):
        number = getattr(header, name, None)
        if number is not None:
            body[key] = quantity(number)
    if getattr(header, "withdrawals_root", None) is not None:
        body["withdrawals"] = []
    return body


def created_address(sender: bytes, nonce: int) -> bytes:
    """The address a contract-creating transaction from ``sender`` with ``nonce`` creates."""
    return keccak(rlp.encode([sender, nonce]))[12:]


def receipt(
    value: BlockAPI, receipts: tuple[ReceiptAPI, ...], index: int, tx: SignedTransactionAPI
) -> dict[str, Any]:
    """The receipt of ``tx``, the block's ``index``-th transaction (passed in so that a
    sender already recovered is not recovered again)."""
    contract = None if tx.to else created_address(tx.sender, tx.nonce)
    this = receipts[index]
    logs = [entry for entry in block_logs(value, receipts) if entry.tx_index == index]
    return {
        "transactionHash": data(tx.hash),
        "transactionIndex": quantity(index),
        "blockHash": data(value.hash),
        "blockNumber": quantity(value.number),
        "from": address(tx.sender),
        "to": address(tx.to) if tx.to else None,
        "cumulativeGasUsed": quantity(this.gas_used),
        "gasUsed": quantity(gas_used_by(receipts, index)),
        "effectiveGasPrice": quantity(effective_gas_price(tx, base_fee(value.header))),
        "contractAddress": address(contract) if contract else None,
        "logs": [entry.to_rpc() for entry in logs],
        "logsBloom": data(this.bloom.to_bytes(256, "big")),
        "status": quantity(receipt_status(this)),
        "type": quantity(tx.type_id or 0),
    }


def checksum(value: bytes) -> str:
    return str(to_checksum_address(value))
