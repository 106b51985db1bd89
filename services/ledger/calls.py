"""``eth_call`` and ``eth_estimateGas`` on a snapshot, bounded in gas and in wall time.

A call is free for the caller, so it must be bounded by the node: an infinite loop with
2^63 gas would otherwise run forever. As geth does (``--rpc.gascap``, ``--rpc.evmtimeout``),
the gas a call may use is capped and its execution is aborted after a wall-clock limit.

Calls never take the chain's lock: each worker thread reads the store through its own
read-only SQLite connection (WAL lets it read the last committed state while a block is being
mined), and a call executes on the state root of the block it names, which no later block
changes. So a slow call delays nobody's transaction or read.

Because that state never changes, each thread keeps the py-evm state it built for the last
mined block it ran a call on and runs the next call at that block on it again: every call runs
inside a snapshot that is reverted, so what stays behind is only py-evm's read caches (decoded
accounts, trie lookups, code). Building the state and walking the trie again cost more than
executing a typical view call.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar, cast

from eth.abc import (
    BlockHeaderAPI,
    ComputationAPI,
    SignedTransactionAPI,
    StateAPI,
    TransactionContextAPI,
)
from eth.consensus.applier import ConsensusApplier
from eth.consensus.noproof import NoProofConsensus
from eth.exceptions import Revert
from eth.vm.chain_context import ChainContext
from eth.vm.forks.frontier.validation import validate_frontier_transaction
from eth.vm.forks.prague import PragueVM
from eth.vm.forks.prague.state import PragueTransactionExecutor
from eth_typing import Address, Hash32

from services.ledger.chaindb import DevChain, DurableAtomicDB
from services.ledger.precompile_budget import (
    PRECOMPILE_CHECK_GAS,
    BudgetedComputation,
    BudgetedState,
)

T = TypeVar("T")


class CallTimeout(Exception):
    """The call ran past the wall-clock limit; deliberately not a VMError, so it unwinds all."""


class OverBudget(Exception):
    """A call given a budget shorter than the configured limit ran past it; nothing of it
    remains, so it can be run again with the whole limit."""


@dataclass(frozen=True)
class CallLimits:
    """``gas_cap`` None means the block gas limit, geth's own default."""

    gas_cap: int | None = None
    timeout_s: float = 5.0

    def gas_for(self, requested: int | None, block_gas_limit: int) -> int:
        cap = self.gas_cap if self.gas_cap is not None else block_gas_limit
        return cap if requested is None else min(requested, cap)


class BoundedComputation(BudgetedComputation):
    """Checks its call's deadline each time an opcode is charged its gas, and before a slow
    precompile runs, against what its charge will take: one run of a precompile cannot be
    stopped half-way, and 40 bn254 pairings took 7 s past a 5 s timeout."""

    state: CallState

    def consume_gas(self, amount: int, reason: str) -> None:
        """The budget check of a mined transaction, so that a call and ``eth_estimateGas``
        answer what mining will do, then the deadline's; without ``super()``'s frame."""
        now = time.monotonic()
        if now > self.state.deadline:
            raise CallTimeout(reason)
        if (
            amount >= PRECOMPILE_CHECK_GAS
            and now + self.spend_precompile_budget(amount, reason) > self.state.deadline
        ):
            raise CallTimeout(reason)
        self._gas_meter.consume_gas(amount, reason)


AccessEntries = tuple[tuple[bytes, tuple[int, ...]], ...]
"""An EIP-2930 access list: addresses, each with its storage slots."""


class AccessRecorder:
    """Every account and storage slot a call warms, in order of first access."""

    def __init__(self) -> None:
        self.accounts: dict[bytes, dict[int, None]] = {}

    def account(self, address: bytes) -> None:
        self.accounts.setdefault(bytes(address), {})

    def slot(self, address: bytes, slot: int) -> None:
        self.accounts.setdefault(bytes(address), {})[slot] = None

    def entries(self, excluded: set[bytes]) -> AccessEntries:
        """As geth's access-list tracer: ``excluded`` accounts (sender, recipient, coinbase,
        precompiles: warm anyway) appear only for the slots touched in them."""
        return tuple(
            (address, tuple(slots))
            for address, slots in self.accounts.items()
            if slots or (address not in excluded and not _is_precompile(address))
        )


def _is_precompile(address: bytes) -> bool:
    """Prague's precompiles sit at 0x01 to 0x11."""
    return address[:19] == bytes(19) and 1 <= address[19] <= 0x11


class CallExecutor(PragueTransactionExecutor):
    """Runs a call as py-evm runs a transaction, less the finalization: refunding the
    sender, paying the coinbase and clearing touched empty accounts change only state that
    the call's snapshot throws away (its output, error, gas and refund counter are known by
    then), and cost a tenth of a small call."""

    def finalize_computation(
        self, transaction: SignedTransactionAPI, computation: ComputationAPI
    ) -> ComputationAPI:
        return computation


class CallState(BudgetedState):
    """A free call's state: the block's base fee stays visible to ``BASEFEE``, but the call
    pays nothing, so the fee checks of a real transaction do not apply (geth's NoBaseFee);
    the sender's nonce and its balance for the value still do. ``recorder``, when set,
    sees every account and slot the call warms (``eth_createAccessList``)."""

    computation_class = BoundedComputation
    transaction_executor_class = CallExecutor
    recorder: AccessRecorder | None = None
    deadline = math.inf
    """``time.monotonic()`` past which the call running on this state stops."""
    gas_price = 0
    """What ``GASPRICE`` reads in the call running on this state."""

    def get_transaction_context(self, transaction: SignedTransactionAPI) -> TransactionContextAPI:
        """The call's context with its own ``GASPRICE``: py-evm's way of overriding it copies
        the transaction twice per call."""
        return self.get_transaction_context_class()(
            gas_price=self.gas_price, origin=transaction.sender
        )

    def mark_address_warm(self, address: Address) -> None:
        if self.recorder is not None:
            self.recorder.account(address)
        super().mark_address_warm(address)

    def mark_storage_warm(self, address: Address, slot: int) -> None:
        if self.recorder is not None:
            self.recorder.slot(address, slot)
        super().mark_storage_warm(address, slot)

    def validate_transaction(self, transaction: SignedTransactionAPI) -> None:
        validate_frontier_transaction(self, transaction)


class SnapshotChain(DevChain):
    """The development chain's rules with the bounded computation, for reads only."""

    vm_configuration = ConsensusApplier(NoProofConsensus).amend_vm_configuration(
        ((0, PragueVM.configure(_state_class=CallState)),)
    )

    def state_for_call(self, header: BlockHeaderAPI, pending: bool) -> StateAPI:
        """The state a call at ``header`` runs on, in that block's own context.

        As geth and anvil do, a call at a mined block sees that block's number, timestamp,
        base fee and coinbase, on the state after it; ``pending`` sees the block that would
        be mined next (number + 1, the time now, the next base fee) on the same state.
        """
        vm_class = self.get_vm_class(header)
        ancestors = vm_class.get_prev_hashes(header.parent_hash, self.chaindb)
        if pending:
            context = self.create_header_from_parent(header)
            previous: Iterable[Hash32] = itertools.chain((header.hash,), ancestors or ())
        else:
            context, previous = header, ancestors or ()
        return vm_class.build_state(self.chaindb.db, context, ChainContext(self.chain_id), previous)


def execute(state: CallState, transaction: SignedTransactionAPI, gas_price: int) -> ComputationAPI:
    """Run ``transaction`` (priced at zero: it pays nothing) on ``state`` and undo it;
    ``GASPRICE`` reads ``gas_price``."""
    snapshot = state.snapshot()
    state.gas_price = gas_price
    try:
        return state.apply_transaction(transaction)
    finally:
        state.gas_price = 0
        state.revert(snapshot)


STATE_REUSES = 1_000
"""Calls run on one kept state before it is built anew: py-evm logs every account and trie
node a state reads (for witnesses), so a state kept forever would grow without bound."""


@dataclass
class _KeptState:
    """The state a thread built for one mined block, and how many more calls may reuse it."""

    block_hash: bytes
    state: CallState
    uses_left: int


class SnapshotCalls:
    """Runs calls against the store at ``path`` with one read-only chain per thread."""

    def __init__(self, path: Path, limits: CallLimits) -> None:
        self.path = path
        self.limits = limits
        self._local = threading.local()
        self._opened: list[DurableAtomicDB] = []
        self._opened_lock = threading.Lock()

    def run(
        self,
        header: BlockHeaderAPI,
        pending: bool,
        work: Callable[[SnapshotChain, CallState], T],
        timeout_s: float | None = None,
    ) -> T:
        """``work(chain, state)`` on the state a call at ``header`` sees, stopped with
        ``CallTimeout`` after ``timeout_s`` (the configured limit when None).

        The state is kept for the next call at the same block when ``work`` returns or the
        call reverted (execution is undone by then); any other failure may have stopped
        py-evm half-way through a transaction, so that state is dropped.
        """
        chain = self._chain()
        kept = None if pending else self._reusable(header)
        if kept is not None:
            state = kept.state
        else:
            state = cast(CallState, chain.state_for_call(header, pending))
            if not pending:  # a pending block's context holds the time now: never kept
                kept = _KeptState(header.hash, state, STATE_REUSES)
        limit = self.limits.timeout_s if timeout_s is None else timeout_s
        state.deadline = time.monotonic() + limit
        try:
            result = work(chain, state)
        except Revert:
            self._keep(kept)
            raise
        finally:
            state.deadline = math.inf
        self._keep(kept)
        return result

    def _reusable(self, header: BlockHeaderAPI) -> _KeptState | None:
        """This thread's kept state if it is ``header``'s and may be used again; taken out
        until the call ends well."""
        kept: _KeptState | None = getattr(self._local, "kept", None)
        self._local.kept = None
        if kept is None or kept.block_hash != header.hash or not kept.uses_left:
            return None
        return kept

    def _keep(self, kept: _KeptState | None) -> None:
        if kept is not None:
            kept.uses_left -= 1
            self._local.kept = kept

    def _chain(self) -> SnapshotChain:
        chain: SnapshotChain | None = getattr(self._local, "chain", None)
        if chain is None:
            db = DurableAtomicDB(self.path, read_only=True)
            with self._opened_lock:
                self._opened.append(db)
            chain = SnapshotChain(db)
            self._local.chain = chain
        return chain

    def close(self) -> None:
        with self._opened_lock:
            for db in self._opened:
                db.close()
            self._opened.clear()


class GasAllowanceExceeded(Exception):
    """The call fails even with all the gas it may have (not a revert)."""

    def __init__(self, allowance: int) -> None:
        super().__init__(f"gas required exceeds allowance ({allowance})")
        self.allowance = allowance


ESTIMATE_TOLERANCE = 100
"""The search stops once ``hi - lo <= lo / 100``: the answer is at most 1 % above the least
gas that succeeds (geth stops at 1.5 %)."""
CALL_STIPEND = 2_300


def estimate_gas(
    state: CallState,
    transaction_with_gas: Callable[[int], SignedTransactionAPI],
    gas_price: int,
    allowance: int,
) -> int:
    """The least gas (within 1 %) with which the call succeeds, by geth's binary search.

    One run with the whole ``allowance`` decides whether the call can succeed at all (its
    revert, or ``GasAllowanceExceeded``); the gas it used, net of refunds, bounds the answer
    from below. A first guess just above what it used, plus the stipend and the 63/64 that
    each nested call keeps back, nearly always succeeds, so the search then narrows a small
    range. Failure at a lower gas, whatever its kind, means too little gas.
    """

    def run(gas: int) -> ComputationAPI:
        return execute(state, transaction_with_gas(gas), gas_price)

    whole = transaction_with_gas(allowance)
    if not whole.data and whole.to and not state.get_code(whole.to):
        return int(whole.intrinsic_gas)  # a plain transfer, as geth short-circuits it
    first = run(allowance)
    if first.is_error:
        if isinstance(first.error, Revert):
            first.raise_if_error()
        raise GasAllowanceExceeded(allowance)
    used = allowance - first.get_gas_remaining()
    refund = min(first.get_gas_refund(), used // 5)
    low, high = used - refund - 1, allowance
    optimistic = (used + CALL_STIPEND) * 64 // 63
    if optimistic < high:
        if run(optimistic).is_error:
            low = optimistic
        else:
            high = optimistic
    while low + 1 < high and (high - low) * ESTIMATE_TOLERANCE > low:
        middle = min((high + low) // 2, low * 2)
        if run(middle).is_error:
            low = middle
        else:
            high = middle
    return high


@dataclass(frozen=True)
class AccessList:
    """``eth_createAccessList``'s answer; ``error`` when the call fails even with it."""

    entries: AccessEntries
    gas_used: int
    error: str | None = None


ACCESS_LIST_ROUNDS = 4
"""Listing accounts can change what a call does (it may read its own gas): geth reruns until
the list is stable; so do we, this many times at most."""


def create_access_list(
    state: CallState,
    transaction_with_gas: Callable[..., SignedTransactionAPI],
    gas_price: int,
    allowance: int,
    excluded: set[bytes],
) -> AccessList:
    """The accounts and slots the call touches, and the gas it uses with them listed."""
    entries: AccessEntries = ()
    for _ in range(ACCESS_LIST_ROUNDS):
        recorder = AccessRecorder()
        state.recorder = recorder
        try:
            computation = execute(state, transaction_with_gas(allowance, entries), gas_price)
        finally:
            state.recorder = None
        found = recorder.entries(excluded)
        if found == entries:
            break
        entries = found
    used = allowance - computation.get_gas_remaining()
    gas_used = used - min(computation.get_gas_refund(), used // 5)
    error = None
    if computation.is_error:
        error = (
            "execution reverted"
            if isinstance(computation.error, Revert)
            else str(computation.error)
        )
    return AccessList(entries, gas_used, error)
