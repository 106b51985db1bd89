"""Build, sign, send and confirm transactions with the robot's own key.

Robots sign their own transactions (the ledger never holds a key), so this module does what a
wallet does: estimate gas (which also surfaces a revert before anything is sent), take the
nonce and gas price from the node, sign an EIP-155 transaction for the node's chain id, send it
raw, and poll for the receipt. A mined transaction that reverted is replayed with ``eth_call``
on the state before its block so that the caller gets the contract's reason, not just status 0.

The node is not trusted with what the robot signs: its chain id must be the deployment's when
the robot names one, the gas and gas price it asks are capped (:class:`FeeLimits`), and the
hash it answers for a sent transaction, and the receipt it shows, must be the transaction's own.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import rlp
from eth_utils.address import to_checksum_address
from eth_utils.crypto import keccak

from robocloud import config
from robocloud.errors import InvalidAnswerError
from robocloud.identity import Identity
from robocloud.ledger.abi import ContractAbi, check_block, check_hash
from robocloud.ledger.errors import (
    DeploymentMismatchError,
    FeeLimitError,
    LedgerError,
    RevertError,
    RpcError,
    TransactionMismatchError,
    TransactionTimeoutError,
)
from robocloud.ledger.rpc import JsonRpcClient, as_revert

GAS_MARGIN = 1.25
"""Headroom over ``eth_estimateGas``: storage refunds and warm/cold slots vary between the
estimate and inclusion."""


SIGNING_ATTEMPTS = 5
"""How often ``send`` signs a call again when another writer of the key took its nonce first:
each time that writer got a transaction in, so only as many writers racing at once as this
fail one of them."""

PRICE_BUMP_EIGHTHS = 1
"""A replacement pays the saved transaction's gas price plus an eighth (12.5 %): nodes take a
transaction in the place of another of the same nonce only at 10 % more (geth, anvil)."""

NONCE_TAKEN = ("nonce too low", "replacement transaction underpriced")
"""How nodes (geth, anvil, the ledger) refuse a transaction whose nonce another transaction of
its sender holds, mined or waiting: never included, so signing the call again is safe."""

_QUANTITY = re.compile(r"0x[0-9a-fA-F]{1,64}")


def quantity(value: Any) -> int:
    """A JSON-RPC quantity (``0x`` and at most 64 hex digits) as an int.

    It comes from a node, so anything else (``null``, ``"0xzz"``, a number) is an
    ``InvalidAnswerError``, never a ``ValueError`` escaping as a traceback.
    """
    if not isinstance(value, str) or not _QUANTITY.fullmatch(value):
        raise InvalidAnswerError(f"the node sent {value!r:.80} where a quantity belongs")
    return int(value, 16)


@dataclass(frozen=True)
class FeeLimits:
    """The most gas, and the most wei per gas, this robot signs a transaction for.

    Defaults from ``ROBOCLOUD_MAX_GAS`` and ``ROBOCLOUD_MAX_FEE_PER_GAS_GWEI`` (docs/cli.md).
    """

    max_gas: int
    max_fee_per_gas: int

    @classmethod
    def from_env(cls) -> FeeLimits:
        return cls(config.max_gas(), config.max_fee_per_gas())

    def check(self, gas: int, gas_price: int) -> None:
        """Raise ``FeeLimitError`` for a transaction over either limit."""
        if gas > self.max_gas:
            raise FeeLimitError(
                f"refused to sign a transaction of {gas} gas: this robot pays for at most "
                f"{self.max_gas} (ROBOCLOUD_MAX_GAS)"
            )
        if gas_price > self.max_fee_per_gas:
            raise FeeLimitError(
                f"refused to sign at the node's gas price of {gas_price / config.GWEI:g} gwei: "
                f"this robot pays at most {self.max_fee_per_gas / config.GWEI:g} gwei per gas "
                "(ROBOCLOUD_MAX_FEE_PER_GAS_GWEI)"
            )


MAX_CHAIN_ID = (2**64 - 1) // 2 - 36
"""EIP-2294's bound, so that an EIP-155 ``v`` (``2 * chainId + 36``) fits in 64 bits. It
also fits the storage node's SQLite integers: the 2^64 - 1 allowed before let a chain id
past 2^63 be signed for and sent, then raise OverflowError recording the anchor, forever."""


def check_chain(found: int, expected: int | None) -> int:
    """``found``, the node's chain id, if it is the one the robot expects (None: any) and
    within EIP-2294's bound (``MAX_CHAIN_ID``)."""
    if found > MAX_CHAIN_ID:
        raise InvalidAnswerError(f"the node serves chain {found}, past EIP-2294's {MAX_CHAIN_ID}")
    if expected is not None and found != expected:
        raise DeploymentMismatchError(
            f"the node serves chain {found}, but the robot's deployment is on chain {expected} "
            "(ROBOCLOUD_EXPECTED_DEPLOYMENT)"
        )
    return found


def transaction_hash(raw: bytes) -> str:
    """The hash of a signed transaction: keccak-256 of its raw bytes, ``0x``-hex."""
    return "0x" + keccak(raw).hex()


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
    def from_rpc(cls, raw: Any) -> Receipt:
        """A node's receipt; a malformed one is an ``InvalidAnswerError``."""
        try:
            logs = raw.get("logs") or []
            if not isinstance(logs, list):
                raise TypeError(f"logs is {type(logs).__name__}, not a list")
            return cls(
                tx_hash=check_hash(raw["transactionHash"]),
                block_number=check_block(quantity(raw["blockNumber"])),
                block_hash=check_hash(raw["blockHash"]),
                status=_status(raw["status"]),
                gas_used=quantity(raw["gasUsed"]),
                contract_address=(
                    to_checksum_address(raw["contractAddress"])
                    if raw.get("contractAddress")
                    else None
                ),
                logs=logs,
            )
        except (AttributeError, KeyError, TypeError, ValueError) as exc:
            raise InvalidAnswerError(
                f"the node sent a malformed transaction receipt ({type(exc).__name__}: "
                f"{str(exc)[:200]})"
            ) from exc


def _status(value: Any) -> int:
    """A receipt's status, 1 (success) or 0 (reverted): any other was taken for success."""
    status = quantity(value)
    if status not in (0, 1):
        raise ValueError(f"status {status}, neither 0 nor 1")
    return status


MAX_NONCE = 2**64 - 2
"""The highest nonce a transaction may carry (EIP-2681: an account's nonce stops below 2^64-1)."""


def _nonce(value: Any) -> int:
    """The node's next nonce for the robot, refused past EIP-2681's bound: a transaction
    signed with it could never be mined, only kept by the node."""
    nonce = quantity(value)
    if nonce > MAX_NONCE:
        raise InvalidAnswerError(f"the node sent the nonce {nonce}, past EIP-2681's {MAX_NONCE}")
    return nonce


_nonce_locks: dict[tuple[int, str], threading.Lock] = {}
_nonce_locks_guard = threading.Lock()


def nonce_lock(chain_id: int, address: str) -> threading.Lock:
    """The lock every ``Transactor`` of this process holds for ``address`` on ``chain_id``
    from reading its pending nonce until the node has accepted the transaction signed with it.

    A storage node's anchorer and dataset publisher sign with one key, each through a
    ``Ledger`` of its own: both read the same pending nonce, and the node refused one of the two
    transactions ("nonce too low"), failing that anchor or publish. The nonce still comes from
    the node each time (none is counted here, so a transaction the node dropped leaves no gap
    behind it); the lock only orders the writers. Other processes signing with the key are not
    covered by it: ``Transactor.send`` signs again when one of them took the nonce.
    """
    key = (chain_id, address.lower())
    with _nonce_locks_guard:
        return _nonce_locks.setdefault(key, threading.Lock())


def _uint(field: bytes) -> int:
    """An RLP integer field (big-endian, no leading zeros, empty for 0)."""
    return int.from_bytes(field, "big")


def _receipt_of(tx_hash: str, raw: Any) -> Receipt:
    """The receipt the node sent for ``tx_hash``; a malformed one names the hash, since the
    transaction was sent and may be mined."""
    try:
        return Receipt.from_rpc(raw)
    except InvalidAnswerError as exc:
        raise TransactionMismatchError(
            f"the node's receipt for {tx_hash} is unusable: {exc}", tx_hash
        ) from exc


@dataclass(frozen=True)
class SignedTransaction:
    """A signed transaction and its nonce: what a caller saves before sending it, so that
    after a crash it can send the same bytes again (``Transactor.resume``) instead of signing
    another transaction with the next nonce."""

    raw: bytes
    nonce: int

    @property
    def tx_hash(self) -> str:
        return transaction_hash(self.raw)

    def to_json(self) -> dict[str, Any]:
        return {"raw": "0x" + self.raw.hex(), "tx": self.tx_hash, "nonce": self.nonce}

    @classmethod
    def from_json(cls, document: dict[str, Any]) -> SignedTransaction:
        """What ``to_json`` gave; a ``ValueError`` if its hash is not its bytes'."""
        signed = cls(bytes.fromhex(str(document["raw"]).removeprefix("0x")), int(document["nonce"]))
        if signed.tx_hash != document["tx"]:
            raise ValueError(f"saved transaction {document['tx']!r:.80} is not its raw bytes'")
        return signed


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
        chain_id: int | None = None,
        limits: FeeLimits | None = None,
    ) -> None:
        self.rpc = rpc
        self.identity = identity
        self.contracts = contracts or []
        self.receipt_timeout_s = receipt_timeout_s
        self.poll_interval_s = poll_interval_s
        self.expected_chain_id = chain_id
        """The chain the robot means to sign for; None signs for whatever the node serves."""
        self.limits = limits or FeeLimits.from_env()
        self._chain_id: int | None = None

    @property
    def chain_id(self) -> int:
        """The node's chain id, once it was checked against ``expected_chain_id``."""
        if self._chain_id is None:
            found = quantity(self.rpc.request("eth_chainId", []))
            self._chain_id = check_chain(found, self.expected_chain_id)
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
        """The raw signed transaction, with nonce and gas price from the node (see
        ``sign_transaction``)."""
        return self.sign_transaction(to, data, gas=gas, value=value).raw

    def sign_transaction(
        self, to: str | None, data: bytes, *, gas: int, value: int = 0
    ) -> SignedTransaction:
        """The signed transaction, with nonce and gas price from the node.

        The nonce is the node's pending count, so a caller sending what it signs holds
        ``nonce_lock`` until the node has it, as ``send`` does. Raises ``FeeLimitError``
        before signing when the gas or the node's gas price is over ``limits``, and
        ``DeploymentMismatchError`` when the node's chain is not the expected.
        """
        address = self.identity.address
        chain_id = self.chain_id
        gas_price = quantity(self.rpc.request("eth_gasPrice", []))
        self.limits.check(gas, gas_price)
        transaction: dict[str, Any] = {
            "chainId": chain_id,
            "nonce": _nonce(self.rpc.request("eth_getTransactionCount", [address, "pending"])),
            "gas": gas,
            "gasPrice": gas_price,
            "data": data,
            "value": value,
        }
        if to is not None:
            transaction["to"] = to_checksum_address(to)
        signed = self.identity.account.sign_transaction(transaction)
        return SignedTransaction(bytes(signed.raw_transaction), transaction["nonce"])

    def send(
        self,
        to: str | None,
        data: bytes,
        *,
        value: int = 0,
        gas: int | None = None,
        before_send: Callable[[SignedTransaction], None] | None = None,
    ) -> Receipt:
        """Sign, send and wait; raise ``RevertError`` (with the reason) if it reverts.

        Without ``gas`` the gas is estimated, so a call that would revert fails before
        anything is sent and costs nothing. ``before_send`` is given the signed transaction
        before it is sent (under ``nonce_lock``), for a caller to save it durably and
        ``resume`` it after a crash; it is given the new one when the call is signed again.

        ``nonce_lock`` orders the writers of this process; another process signing with the
        key (two CLI commands at once, a second host) can take the nonce between the read and
        the send. The node then refuses the transaction (:data:`NONCE_TAKEN`), and a call
        moving no ether is signed again on a fresh nonce, up to :data:`SIGNING_ATTEMPTS`
        times. Only the node says the nonce was taken: one that lies could mine every variant,
        so one that moves ether is never signed twice, and a contract call at most that often.
        """
        gas = gas if gas is not None else self.estimate_gas(to, data, value)
        for attempt in range(1, SIGNING_ATTEMPTS + 1):
            with nonce_lock(self.chain_id, self.identity.address):
                signed = self.sign_transaction(to, data, gas=gas, value=value)
                if before_send is not None:
                    before_send(signed)
                try:
                    tx_hash = self.submit(signed.raw)
                    break
                except RpcError as exc:
                    last = attempt == SIGNING_ATTEMPTS or value != 0
                    if last or not self._nonce_taken(signed, exc):
                        raise
        receipt = self.wait_for_receipt(tx_hash)
        if receipt.status == 0:
            raise self._revert_of(to, data, value, receipt)
        return receipt

    def submit(self, raw: bytes) -> str:
        """Send a signed transaction; its hash, once the node answered that same hash."""
        tx_hash = transaction_hash(raw)
        answered = self.rpc.request("eth_sendRawTransaction", ["0x" + raw.hex()])
        if not isinstance(answered, str) or answered.lower() != tx_hash:
            raise TransactionMismatchError(
                f"the node answered {str(answered)[:80]!r} to eth_sendRawTransaction, "
                f"but the transaction sent is {tx_hash}",
                tx_hash,
            )
        return tx_hash

    def _nonce_taken(self, signed: SignedTransaction, refusal: RpcError) -> bool:
        """Whether the node refused ``signed`` because another transaction holds its nonce,
        and does not hold ``signed`` itself (a lost answer's resend is refused the same way
        once the first copy is in: that one must be waited for, never signed again)."""
        if not refusal.message.lower().startswith(NONCE_TAKEN):
            return False
        return self.rpc.request("eth_getTransactionByHash", [signed.tx_hash]) is None

    def resume(
        self,
        signed: SignedTransaction,
        *,
        before_send: Callable[[SignedTransaction], None] | None = None,
    ) -> Receipt | None:
        """The receipt of a transaction saved before it was sent by a process that died before
        its receipt: sent again (the same bytes, so one transaction however often it arrives)
        unless the node has it mined, then waited for. None once its nonce went to another
        transaction: it can never be mined, and a new one may be signed.

        Behind an external node a transaction can stay pending past a crash; signing another
        for the same call made both be mined. One still pending after ``receipt_timeout_s``
        (its gas price fell behind the chain's base fee) is replaced, when ``before_send`` is
        given to save the replacement: the same call and nonce at a higher price
        (:meth:`repriced`), so that at most one of them is mined; when the original is mined
        while the replacement is being saved, the node refuses the replacement and the
        original's receipt is the answer. A caller that saves only
        the replacement must look on chain for the call's effect before resuming, since the
        transaction it replaced may still be the one mined (the storage node's anchorer and
        publisher read ``anchorAt`` and the advertisements first).
        """
        receipt = self.receipt(signed.tx_hash)
        if receipt is not None:
            return receipt
        if self._nonce_used(signed):
            return self.receipt(signed.tx_hash)
        try:
            self.submit(signed.raw)
        except RpcError:
            # "already known" (the node kept it), or "nonce too low" (mined or replaced since)
            if self.rpc.request("eth_getTransactionByHash", [signed.tx_hash]) is None:
                if self._nonce_used(signed):
                    return self.receipt(signed.tx_hash)
                raise
        try:
            return self.wait_for_receipt(signed.tx_hash)
        except TransactionTimeoutError:
            if before_send is None or self._nonce_used(signed):
                raise
        replacement = self.repriced(signed)
        before_send(replacement)
        try:
            self.submit(replacement.raw)
        except RpcError:
            # "nonce too low": the original was mined after its wait ended, and is the answer.
            receipt = self.receipt(signed.tx_hash)
            if receipt is None:
                raise
            return receipt
        return self.wait_for_receipt(replacement.tx_hash)

    def repriced(self, signed: SignedTransaction) -> SignedTransaction:
        """``signed``'s call on the same nonce at a higher gas price: an eighth more, or the
        node's price if that is higher still, within ``limits`` (``FeeLimitError`` past them).

        Only a legacy transaction, as this class signs, can be repriced.
        """
        fields = rlp.decode(signed.raw) if signed.raw[:1] >= b"\xc0" else None
        if not isinstance(fields, list) or len(fields) != 9:
            raise LedgerError(f"transaction {signed.tx_hash} is not a legacy transaction")
        nonce, old_price, gas, to, value, data = (
            fields[0],
            _uint(fields[1]),
            _uint(fields[2]),
            fields[3],
            _uint(fields[4]),
            fields[5],
        )
        bumped = old_price + max(old_price * PRICE_BUMP_EIGHTHS // 8, 1)
        gas_price = max(bumped, quantity(self.rpc.request("eth_gasPrice", [])))
        self.limits.check(gas, gas_price)
        transaction: dict[str, Any] = {
            "chainId": self.chain_id,
            "nonce": _uint(nonce),
            "gas": gas,
            "gasPrice": gas_price,
            "data": data,
            "value": value,
        }
        if to:
            transaction["to"] = to_checksum_address(to)
        replacement = self.identity.account.sign_transaction(transaction)
        return SignedTransaction(bytes(replacement.raw_transaction), signed.nonce)

    def _nonce_used(self, signed: SignedTransaction) -> bool:
        """Whether a mined transaction of this key took ``signed``'s nonce."""
        mined = quantity(
            self.rpc.request("eth_getTransactionCount", [self.identity.address, "latest"])
        )
        return signed.nonce < mined

    def deploy(self, contract: ContractAbi, bytecode: str, *args: Any) -> Receipt:
        """Create a contract from its bytecode and constructor arguments."""
        data = bytes.fromhex(bytecode.removeprefix("0x")) + contract.encode_constructor(*args)
        return self.send(None, data)

    def wait_for_receipt(self, tx_hash: str) -> Receipt:
        """Poll for ``tx_hash``'s receipt; one the node shows for another transaction is an
        ``InvalidAnswerError``, never taken for this one's."""
        deadline = time.monotonic() + self.receipt_timeout_s
        while True:
            receipt = self.receipt(tx_hash)
            if receipt is not None:
                return receipt
            if time.monotonic() >= deadline:
                raise TransactionTimeoutError(tx_hash, self.receipt_timeout_s)
            time.sleep(self.poll_interval_s)

    def receipt(self, tx_hash: str) -> Receipt | None:
        """``tx_hash``'s receipt, None while the node has none; one for another transaction
        is a ``TransactionMismatchError``."""
        raw = self.rpc.request("eth_getTransactionReceipt", [tx_hash])
        if raw is None:
            return None
        receipt = _receipt_of(tx_hash, raw)
        if receipt.tx_hash.lower() != tx_hash.lower():
            raise TransactionMismatchError(
                f"asked for the receipt of {tx_hash}, the node answered one of "
                f"{receipt.tx_hash[:80]!r}",
                tx_hash,
            )
        return receipt

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
