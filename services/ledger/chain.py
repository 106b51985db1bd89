"""The embedded development chain: execution, automining and reads over the durable store.

Every accepted transaction is mined at once in its own block (automine, as eth-tester and
hardhat do), and the block is committed to the SQLite store of ``chaindb`` in one fsynced
transaction before ``send_raw_transaction`` returns. A receipt the caller can see is therefore
always on disk, and a restart reopens the store with the same head hash: nothing is replayed.

Transactions are checked here before py-evm sees them so that each refusal has the message
Ethereum nodes use (``nonce too low``, ``invalid chain id``, ``insufficient funds``). The class
is thread-safe: one fair lock serialises writes and the reads that touch py-evm's mutable chain.
"""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from eth.abc import (
    BlockAPI,
    BlockHeaderAPI,
    ReceiptAPI,
    SignedTransactionAPI,
    StateAPI,
    VirtualMachineAPI,
)
from eth.exceptions import BlockNotFound, HeaderNotFound, Revert, TransactionNotFound
from eth.vm.spoof import SpoofTransaction
from eth_typing import Address
from eth_utils.crypto import keccak
from eth_utils.exceptions import ValidationError

from services.common.fairlock import FairLock
from services.ledger import validation
from services.ledger.calls import (
    AccessEntries,
    AccessList,
    CallLimits,
    CallState,
    CallTimeout,
    GasAllowanceExceeded,
    OverBudget,
    SnapshotCalls,
    SnapshotChain,
    create_access_list,
    estimate_gas,
    execute,
)
from services.ledger.chaindb import CHAIN_ID, DevChain, open_chain
from services.ledger.pool import PendingPool, PoolLimits
from services.ledger.refusals import ChainError as ChainError
from services.ledger.refusals import InvalidParams as InvalidParams
from services.ledger.refusals import Reverted as Reverted

log = logging.getLogger("robocloud.ledger.chain")

BlockTag = int | str
"""A block number, or one of ``latest``, ``pending``, ``earliest``, ``safe``, ``finalized``."""

HEAD_TAGS = ("latest", "pending", "safe", "finalized")
BLOB_TRANSACTION_TYPE = 3
RECENT_BLOCKS = 64
PROMOTION_IN_ANSWER_S = 1.0
"""How long the transaction that closes a nonce gap mines its sender's waiting transactions
before it is answered; the promoter thread mines the rest."""


@dataclass(frozen=True)
class CallRequest:
    """An unsigned call as ``eth_call`` and ``eth_estimateGas`` receive it."""

    sender: bytes
    to: bytes
    data: bytes = b""
    value: int = 0
    gas: int | None = None
    gas_price: int | None = None
    max_fee_per_gas: int | None = None
    max_priority_fee_per_gas: int | None = None

    @property
    def fee_cap(self) -> int:
        """What the sender must afford per gas (0: the call is free and checks no balance)."""
        if self.gas_price is not None:
            return self.gas_price
        return self.max_fee_per_gas or 0

    def effective_gas_price(self, base_fee: int) -> int:
        """What ``GASPRICE`` reads, as in a mined transaction with these fees."""
        if self.gas_price is not None:
            return self.gas_price
        if self.max_fee_per_gas is None:
            return 0
        return min(self.max_fee_per_gas, (self.max_priority_fee_per_gas or 0) + base_fee)


@dataclass(frozen=True)
class MinedBlock:
    """A block just committed, with its receipts: what the event index is fed."""

    block: BlockAPI
    receipts: tuple[ReceiptAPI, ...]


@dataclass(frozen=True)
class Submitted:
    """A transaction accepted: the block it was mined in, or None when it waits in the pool."""

    hash: bytes
    mined: MinedBlock | None


@dataclass(frozen=True)
class Located:
    """A transaction and where it sits in the canonical chain."""

    transaction: SignedTransactionAPI
    block: BlockAPI
    index: int


BlockListener = Callable[[MinedBlock], None]


class EmbeddedChain:
    """The durable automining chain with chain id 1337."""

    def __init__(
        self,
        path: Path,
        genesis_state: Mapping[bytes, Any] | None = None,
        call_limits: CallLimits | None = None,
        pool_limits: PoolLimits | None = None,
    ) -> None:
        self._lock = FairLock()
        self._pool = PendingPool(pool_limits or PoolLimits())
        self._promoter = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ledger-promote")
        self._closing = False
        self._chain, self._db = open_chain(path, genesis_state)
        self._transaction_builder = self._chain.get_vm_class(
            self._chain.header
        ).get_transaction_builder()
        self._path = path
        self.call_limits = call_limits or CallLimits()
        self._calls = SnapshotCalls(path, self.call_limits)
        self._listeners: list[BlockListener] = []
        self._recent: OrderedDict[bytes, tuple[SignedTransactionAPI, MinedBlock]] = OrderedDict()
        self._recent_receipts: dict[bytes, tuple[ReceiptAPI, ...]] = {}
        self._head = self._chain.get_canonical_head()

    @property
    def chain_id(self) -> int:
        return CHAIN_ID

    def close(self) -> None:
        """Stop mining waiting transactions (the one in progress ends its block), then close."""
        with self._lock:
            self._closing = True
        self._promoter.shutdown(wait=True, cancel_futures=True)
        self._calls.close()
        with self._lock:
            self._db.close()

    def exclusive(self) -> FairLock:
        """The chain's lock, to hold over calls that no other transaction may come between
        (an operator key's pending nonce and the transaction that uses it)."""
        return self._lock

    def on_block(self, listener: BlockListener) -> None:
        """Call ``listener`` with every block mined from now on, before its sender is answered."""
        self._listeners.append(listener)

    # ----- blocks -----

    def head(self) -> BlockHeaderAPI:
        """The last mined block's header; read without the lock (one attribute, replaced
        whole after each commit), so that it never waits for a block being mined."""
        return self._head

    def header_at(self, tag: BlockTag) -> BlockHeaderAPI:
        """The header a tag names; every mined block is final, so all named tags but
        ``earliest`` are the head (read without the lock, as ``head`` is)."""
        if tag in HEAD_TAGS:
            return self._head
        with self._lock:
            if tag == "earliest":
                return self._chain.get_canonical_block_header_by_number(0)  # type: ignore[arg-type]
            if not isinstance(tag, int) or tag < 0:
                raise InvalidParams(f"invalid block tag {tag!r}")
            try:
                return self._chain.get_canonical_block_header_by_number(tag)  # type: ignore[arg-type]
            except HeaderNotFound as exc:
                raise ChainError(
                    f"block {tag} not found (head is {self.head().block_number})"
                ) from exc

    def block_by_number(self, tag: BlockTag) -> BlockAPI | None:
        with self._lock:
            try:
                header = self.header_at(tag)
            except ChainError:
                if isinstance(tag, int) and tag >= 0:
                    return None
                raise
            return self._chain.get_block_by_header(header)

    def canonical_hashes(self, first: int, last: int) -> list[bytes]:
        """The hashes of the mined blocks from ``first`` to ``last``: one key lookup each, not
        a block read (a block filter's poll may span ten thousand blocks)."""
        hashes = []
        with self._lock:
            for number in range(first, last + 1):
                try:
                    hashes.append(bytes(self._chain.chaindb.get_canonical_block_hash(number)))  # type: ignore[arg-type]
                except HeaderNotFound:
                    break
        return hashes

    def block_by_hash(self, block_hash: bytes) -> BlockAPI | None:
        with self._lock:
            try:
                block = self._chain.get_block_by_hash(block_hash)  # type: ignore[arg-type]
            except (BlockNotFound, HeaderNotFound):
                return None
            if self._chain.get_canonical_block_hash(block.number) != block.hash:
                return None
            return block

    def receipts(self, block: BlockAPI) -> tuple[ReceiptAPI, ...]:
        recent = self._recent_receipts.get(block.hash)
        if recent is not None:
            return recent
        with self._lock:
            return tuple(block.get_receipts(self._chain.chaindb))

    def recent(self, tx_hash: bytes) -> Located | None:
        """A transaction among the last mined, without the lock (a lookup in a dict that
        only the mining thread changes): the receipt a client asks for right after sending
        is answered without waiting for the next block, and without a worker thread."""
        found = self._recent.get(tx_hash)
        return Located(found[0], found[1].block, 0) if found is not None else None

    def recent_receipts(self, block_hash: bytes) -> tuple[ReceiptAPI, ...] | None:
        return self._recent_receipts.get(block_hash)

    def is_waiting(self, tx_hash: bytes) -> bool:
        """Whether a transaction waits in the pool, without the lock: a robot polling for
        its receipt is answered null at once, not after the blocks being mined."""
        return self._pool.find(tx_hash) is not None

    def waiting(self, tx_hash: bytes) -> SignedTransactionAPI | None:
        """A transaction accepted but waiting in the pool for its sender's nonce gap."""
        with self._lock:
            self._pool.expire()
            return self._pool.find(tx_hash)

    def locate(self, tx_hash: bytes) -> Located | None:
        """Where a mined transaction is, from py-evm's own hash index (not a scan).

        Recently mined transactions are answered from memory with the very object that was
        validated: one read back from the store is a new object whose sender must be
        recovered again (an ECDSA recovery, 5 ms in pure Python), and a receipt is asked
        for right after its transaction is sent.
        """
        with self._lock:
            recent = self._recent.get(tx_hash)
            if recent is not None:
                return Located(recent[0], recent[1].block, 0)
            try:
                number, index = self._chain.get_canonical_transaction_index(tx_hash)  # type: ignore[arg-type]
            except TransactionNotFound:
                return None
            block = self._chain.get_canonical_block_by_number(number)
            return Located(block.transactions[index], block, index)

    # ----- accounts -----

    def balance(self, address: bytes, tag: BlockTag) -> int:
        with self._lock:
            return int(self._state(tag).get_balance(address))

    def nonce(self, address: bytes, tag: BlockTag) -> int:
        with self._lock:
            return int(self._state(tag).get_nonce(address))

    def code(self, address: bytes, tag: BlockTag) -> bytes:
        with self._lock:
            return bytes(self._state(tag).get_code(address))

    def storage_at(self, address: bytes, slot: int, tag: BlockTag) -> int:
        with self._lock:
            return int(self._state(tag).get_storage(address, slot))

    def next_header(self, header: BlockHeaderAPI) -> BlockHeaderAPI:
        """The header a child of ``header`` would have (its base fee, its blob fields)."""
        with self._lock:
            return self._chain.create_header_from_parent(header)

    def base_fee(self) -> int:
        """The base fee the next block will charge."""
        with self._lock:
            return self.base_fee_locked()

    def base_fee_locked(self) -> int:
        """The next block's base fee, under the chain's lock (it follows from the head alone)."""
        return int(self._chain.header.base_fee_per_gas or 0)

    def _state(self, tag: BlockTag) -> Any:
        return self._chain.get_vm(at_header=self.header_at(tag)).state

    # ----- execution -----

    def call(self, request: CallRequest, tag: BlockTag, budget_s: float | None = None) -> bytes:
        """Run a call in block ``tag``'s context; raise ``Reverted`` with its reason.

        With ``budget_s`` the call is abandoned with ``OverBudget`` once it runs that long
        (a caller that must not be held up tries it cheaply first, then runs it elsewhere).
        """
        return bytes(self._execute(request, tag, "call", budget_s))

    def estimate_gas(self, request: CallRequest, tag: BlockTag) -> int:
        """The least gas (within 1 %) with which the call succeeds; ``Reverted`` if it never
        does."""
        return int(self._execute(request, tag, "estimate"))

    def create_access_list(self, request: CallRequest, tag: BlockTag) -> AccessList:
        """The accounts and slots the call touches, and its gas with them listed."""
        found: AccessList = self._execute(request, tag, "access_list")
        return found

    def _execute(
        self,
        request: CallRequest,
        tag: BlockTag,
        mode: Literal["call", "estimate", "access_list"],
        budget_s: float | None = None,
    ) -> Any:
        """Run an unsigned ``request`` on a snapshot, with py-evm's failures as ChainErrors.

        Only finding a block by number takes the chain's lock; the execution itself does not.
        """
        header = self.header_at(tag)
        pending = tag == "pending"
        estimate = mode == "estimate"

        def work(chain: SnapshotChain, state: CallState) -> Any:
            allowance = self._allowance(request, state, header.gas_limit, estimate)
            vm_class = chain.get_vm_class(header)
            nonce = state.get_nonce(Address(request.sender))

            def transaction_with_gas(gas: int, access_list: AccessEntries = ()) -> Any:
                fields: dict[str, Any] = {
                    "nonce": nonce,
                    "gas_price": 0,
                    "gas": gas,
                    "to": request.to,
                    "value": request.value,
                    "data": request.data,
                }
                if access_list:
                    builder = vm_class.get_transaction_builder()
                    unsigned: Any = builder.new_unsigned_access_list_transaction(  # type: ignore[attr-defined]
                        chain_id=CHAIN_ID, access_list=access_list, **fields
                    )
                else:
                    unsigned = vm_class.create_unsigned_transaction(**fields)
                return SpoofTransaction(unsigned, from_=request.sender)

            intrinsic = int(transaction_with_gas(allowance).intrinsic_gas)
            if allowance < intrinsic:
                if estimate:
                    raise GasAllowanceExceeded(allowance)
                raise ChainError(
                    f"intrinsic gas too low: gas {allowance}, minimum needed {intrinsic}"
                )
            price = request.effective_gas_price(int(state.execution_context.base_fee_per_gas or 0))
            if estimate:
                return estimate_gas(state, transaction_with_gas, price, allowance)
            if mode == "access_list":
                excluded = {request.sender, request.to, bytes(header.coinbase)}
                return create_access_list(state, transaction_with_gas, price, allowance, excluded)
            computation = execute(state, transaction_with_gas(allowance), price)
            computation.raise_if_error()
            return computation.output

        try:
            return self._calls.run(header, pending, work, budget_s)
        except CallTimeout as exc:
            if budget_s is not None:
                raise OverBudget() from exc
            raise ChainError(
                f"execution aborted (timeout = {self.call_limits.timeout_s:g}s)"
            ) from exc
        except GasAllowanceExceeded as exc:
            raise ChainError(str(exc)) from exc
        except Revert as exc:
            raise Reverted(bytes(exc.args[0]) if exc.args else b"") from exc
        except ValidationError as exc:
            raise ChainError(str(exc)) from exc
        except Exception as exc:
            if type(exc).__module__.startswith("eth."):
                raise ChainError(f"execution failed: {type(exc).__name__} {exc}") from exc
            raise

    def _allowance(
        self, request: CallRequest, state: Any, block_gas_limit: int, estimate: bool
    ) -> int:
        """The gas the call runs with, checked against what its sender can pay, as geth does:
        a priced call must be affordable; an estimate searches no higher than affordable,
        nor than a transaction may carry (EIP-7825)."""
        allowance = self.call_limits.gas_for(request.gas, block_gas_limit)
        if estimate:
            allowance = min(allowance, validation.MAX_TRANSACTION_GAS)
        balance = int(state.get_balance(Address(request.sender)))
        fee_cap = request.fee_cap
        if fee_cap and estimate and balance >= request.value:
            allowance = min(allowance, (balance - request.value) // fee_cap)
        want = allowance * fee_cap + request.value
        if balance < want:
            raise ChainError(
                f"insufficient funds for gas * price + value: address 0x{request.sender.hex()} "
                f"have {balance} want {want}"
            )
        return allowance

    # ----- transactions -----

    def decode(self, raw: bytes) -> SignedTransactionAPI:
        """A signed transaction from its raw bytes, or ``InvalidParams`` saying why not."""
        if not raw:
            raise InvalidParams("invalid raw transaction: empty")
        validation.check_raw_size(raw)
        if raw[0] == BLOB_TRANSACTION_TYPE:
            raise ChainError("blob transactions (type 3) are not supported by this chain")
        builder = self._transaction_builder
        try:
            transaction = builder.decode(raw)
            transaction.sender  # noqa: B018 - recovers the signer, which can fail
        except Exception as exc:  # any failure to parse untrusted bytes means "invalid"
            raise InvalidParams(f"invalid raw transaction: {type(exc).__name__}: {exc}") from exc
        return transaction

    def send_raw_transaction(self, raw: bytes) -> Submitted:
        """Validate ``raw`` and mine it in a new block, durable before this returns; or, if
        its nonce is ahead of its sender's, queue it until the gap closes.

        The sender's waiting transactions that this one makes next are mined before the
        answer for at most ``PROMOTION_IN_ANSWER_S``, and by the promoter thread after it:
        64 blocks of 2^24 gas held the answer minutes, past any client's timeout, for a
        transaction mined long before; and a few transfers are mined fastest at once."""
        transaction = self.decode(raw)
        with self._lock:
            self._pool.expire()
            vm = self._next_vm()
            if self._check(transaction, vm.state):
                self._pool.add(transaction)
                return Submitted(transaction.hash, None)
            mined = self._mine(transaction, vm)
        if self._promote_logged(transaction.sender, time.monotonic() + PROMOTION_IN_ANSWER_S):
            self._promote_later(transaction.sender)
        return Submitted(transaction.hash, mined)

    def _next_vm(self) -> VirtualMachineAPI:
        """The VM of the block to mine next: the time now (at least the parent's + 1, which
        the pending header holds) and ``prevrandao`` keccak of the parent hash."""
        pending = self._chain.header
        return self._chain.next_vm(
            max(pending.timestamp, int(time.time())), keccak(pending.parent_hash)
        )

    def _promote(self, sender: bytes, deadline: float = math.inf) -> bool:
        """Mine the sender's waiting transactions while each is the next by nonce; one no
        longer valid (its sender's balance fell) is dropped, and the rest wait again. True
        when ``deadline`` came first.

        One block a turn of the lock: the lock is fair, so every read that came meanwhile
        goes before the next block."""
        while not self._closing:
            if time.monotonic() >= deadline:
                return True
            with self._lock:
                if not self._promote_one(sender):
                    return False
        return False

    def _promote_later(self, sender: bytes) -> None:
        with self._lock:
            if not self._closing:
                self._promoter.submit(self._promote_logged, sender)

    def _promote_logged(self, sender: bytes, deadline: float = math.inf) -> bool:
        """``_promote``, a failure (a disk error mining a waiting transaction) logged: the
        transaction that let them through is mined and durable by then, and raising answered
        it as failed, so its robot signed it again and was told "nonce too low". True when
        the promoter thread should go on: the deadline came, or a failure in the answer's
        turn (the thread tries once more)."""
        try:
            return self._promote(sender, deadline)
        except Exception:
            log.exception(
                "mining waiting transactions failed", extra={"sender": "0x" + sender.hex()}
            )
            return deadline != math.inf

    def _promote_one(self, sender: bytes) -> bool:
        """Mine the sender's next waiting transaction; False when none is next (or it was
        dropped)."""
        if not self._pool.waiting(sender):
            return False
        vm = self._next_vm()
        waiting = self._pool.take(sender, vm.state.get_nonce(Address(sender)))
        if waiting is None:
            return False
        try:
            self._check(waiting, vm.state)
            self._mine(waiting, vm)
        except ChainError as exc:
            log.info(
                "waiting transaction dropped",
                extra={"tx": "0x" + waiting.hash.hex(), "reason": exc.message},
            )
            return False
        except Exception:
            self._pool.add(waiting)  # not mined (a disk error): it waits again, not lost
            raise
        return True

    def _check(self, transaction: SignedTransactionAPI, state: StateAPI) -> bool:
        """Every validity rule, in geth's order: the transaction's own fields, then its
        sender's account in ``state``, the head's (code, nonce, balance) and the next
        block's base fee. True when the transaction is valid but for a nonce ahead of its
        sender's."""
        validation.check_fields(transaction, CHAIN_ID, self._head.gas_limit)
        sender = transaction.sender
        validation.check_sender(transaction, bytes(state.get_code(sender)), self.base_fee_locked())
        expected = state.get_nonce(sender)
        if transaction.nonce < expected:
            raise ChainError(
                f"nonce too low: address 0x{sender.hex()} has nonce {expected}, "
                f"transaction has {transaction.nonce}"
            )
        cost = validation.max_cost(transaction)
        balance = state.get_balance(sender)
        if balance < cost:
            raise ChainError(
                f"insufficient funds for gas * price + value: balance {balance}, cost {cost}"
            )
        return bool(transaction.nonce > expected)

    def _mine(self, transaction: SignedTransactionAPI, vm: VirtualMachineAPI) -> MinedBlock:
        """Execute and mine one block on ``vm`` as one SQLite transaction (one fsync, all or
        nothing).

        The pending header got the time now in ``_next_vm``, not when the previous block was
        mined (only its timestamp changes: the base fee and blob fields follow from the
        parent alone, so rebuilding the whole header would be wasted). Listeners run after
        the commit: a failing listener cannot undo an acknowledged block (the event index
        catches up from the store).
        """
        try:
            with self._db.store.transaction():
                block, receipts = self._chain.mine_one(vm, transaction)
        except ValidationError as exc:
            self._chain = DevChain(self._db)
            raise ChainError(str(exc)) from exc
        except BaseException:
            self._chain = DevChain(self._db)
            raise
        mined = MinedBlock(block, receipts)
        self._recent[transaction.hash] = (transaction, mined)
        self._recent_receipts[mined.block.hash] = mined.receipts
        if len(self._recent) > RECENT_BLOCKS:
            _, (_, oldest) = self._recent.popitem(last=False)
            self._recent_receipts.pop(oldest.block.hash, None)
        for listener in self._listeners:
            try:
                listener(mined)
            except Exception:
                log.exception("block listener failed", extra={"block": mined.block.number})
        self._head = mined.block.header  # last: a reader seeing it finds the block indexed
        return mined


def receipt_logs_index_base(receipts: tuple[ReceiptAPI, ...], index: int) -> int:
    """The block-wide index of the first log of the ``index``-th receipt."""
    return sum(len(receipt.logs) for receipt in receipts[:index])


def gas_used_by(receipts: tuple[ReceiptAPI, ...], index: int) -> int:
    """Receipts carry cumulative gas; one transaction's gas is the difference."""
    before = receipts[index - 1].gas_used if index else 0
    return int(receipts[index].gas_used - before)


def receipt_status(receipt: ReceiptAPI) -> int:
    """1 for success, 0 for failure: post-Byzantium receipts keep it in ``state_root``."""
    return 1 if receipt.state_root == b"\x01" else 0
