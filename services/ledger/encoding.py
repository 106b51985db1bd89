"""py-evm's blocks, transactions, receipts and logs in Ethereum JSON-RPC form.

JSON-RPC quantities are ``0x``-hex without leading zeros, data is ``0x``-hex of its bytes,
addresses are lower-case hex (checksums are the client's business, as with geth). These are
the shapes web3.py, ethers and the SDK parse, so they follow the execution-apis spec field by
field rather than eth-tester's Python-side representation.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import rlp
from eth.abc import BlockAPI, BlockHeaderAPI, ReceiptAPI, SignedTransactionAPI
from eth.vm.forks.prague.constants import SET_CODE_TRANSACTION_TYPE
from eth_utils.address import to_checksum_address
from eth_utils.crypto import keccak

from robocloud.errors import InvalidAnswerError, shown_text
from robocloud.ledger.abi import check_hash, uint64_quantity
from services.ledger.chain import gas_used_by, receipt_status

ZERO_ADDRESS = b"\x00" * 20
T = TypeVar("T")


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
    def from_rpc(cls, log: Any) -> LogEntry:
        """Parse a log object another node sent (external-node mode), field by field as the
        spec writes it, or refuse it as the node's ``InvalidAnswerError`` naming the field.

        ``int(x, 16)`` took ``-5`` and numbers of any size: a negative block was stored, and
        a log of block 2^63 failed every indexing round with OverflowError, forever. Numbers
        are strict quantities (the SDK's parser) that SQLite holds; hashes and topics are 32
        bytes, the address 20.
        """
        if not isinstance(log, dict):
            raise InvalidAnswerError(
                f"the node answered eth_getLogs with {shown_text(repr(log))} for a log object"
            )
        return cls(
            block_number=_field(log, "blockNumber", _stored_number),
            block_hash=_field(log, "blockHash", _hash),
            tx_hash=_field(log, "transactionHash", _hash),
            tx_index=_field(log, "transactionIndex", _stored_number),
            log_index=_field(log, "logIndex", _stored_number),
            address=_field(log, "address", _address),
            topics=_field(log, "topics", _topics),
            data=_field(log, "data", _data),
        )


MAX_SQLITE_INTEGER = 2**63 - 1
"""SQLite's largest integer: the event index stores block numbers, indexes and times as they
are, so a node's log naming a larger one is refused before it reaches the index."""
MAX_TOPICS = 4
_DATA = re.compile(r"0x(?:[0-9a-fA-F]{2})*")
_ADDRESS = re.compile(r"0x[0-9a-fA-F]{40}")


def _field(log: dict[str, Any], name: str, parse: Callable[[Any], T]) -> T:
    """``parse`` of the log's ``name``; a refusal names the field (the parsers show its
    value, cut short)."""
    try:
        return parse(log.get(name))
    except ValueError as exc:
        raise InvalidAnswerError(
            f"the node answered eth_getLogs with a malformed log: {name}: {exc}"
        ) from None


def _stored_number(value: Any) -> int:
    """A block number or index, refused past SQLite's integers (2^63 - 1, also the last
    block geth can name): the index stores them as they are."""
    number = uint64_quantity(value)
    if number > MAX_SQLITE_INTEGER:
        raise ValueError(f"{number} is past 2^63 - 1, the largest integer the index holds")
    return number


def _hash(value: Any) -> bytes:
    return bytes.fromhex(check_hash(value)[2:])


def _address(value: Any) -> bytes:
    if not isinstance(value, str) or not _ADDRESS.fullmatch(value):
        raise ValueError(f"{str(value)[:80]!r} is not an address (0x and 40 hex digits)")
    return bytes.fromhex(value[2:])


def _topics(value: Any) -> tuple[bytes, ...]:
    if not isinstance(value, list) or len(value) > MAX_TOPICS:
        shown = f"{len(value)} topics" if isinstance(value, list) else f"{str(value)[:80]!r}"
        raise ValueError(f"{shown}, not a list of at most {MAX_TOPICS} topics")
    return tuple(_hash(topic) for topic in value)


def _data(value: Any) -> bytes:
    if not isinstance(value, str) or not _DATA.fullmatch(value):
        raise ValueError(f"{str(value)[:80]!r} is not 0x-hex bytes")
    return bytes.fromhex(value[2:])


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
