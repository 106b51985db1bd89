"""``eth_call`` and ``eth_estimateGas`` on a snapshot, bounded in gas and in wall time.

A call is free for the caller, so it must be bounded by the node: an infinite loop with
2^63 gas would otherwise run forever. As geth does (``--rpc.gascap``, ``--rpc.evmtimeout``),
the gas a call may use is capped and its execution is aborted after a wall-clock limit.

Calls never take the chain's lock: each worker thread reads the store through its own
read-only SQLite connection (WAL lets it read the last committed state while a block is being
mined), and a call executes on the state root of the block it names, which no later block
changes. So a slow call delays nobody's transaction or read.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from eth.abc import BlockHeaderAPI
from eth.consensus.applier import ConsensusApplier
from eth.consensus.noproof import NoProofConsensus
from eth.vm.forks.prague import PragueVM
from eth.vm.forks.prague.computation import PragueComputation
from eth.vm.forks.prague.state import PragueState

from services.ledger.chaindb import DevChain, DurableAtomicDB

T = TypeVar("T")


class CallTimeout(Exception):
    """The call ran past the wall-clock limit; deliberately not a VMError, so it unwinds all."""


@dataclass(frozen=True)
class CallLimits:
    """``gas_cap`` None means the block gas limit, geth's own default."""

    gas_cap: int | None = None
    timeout_s: float = 5.0

    def gas_for(self, requested: int | None, block_gas_limit: int) -> int:
        cap = self.gas_cap if self.gas_cap is not None else block_gas_limit
        return cap if requested is None else min(requested, cap)


_deadline = threading.local()


class BoundedComputation(PragueComputation):
    """Checks the calling thread's deadline each time an opcode is charged its gas."""

    def consume_gas(self, amount: int, reason: str) -> None:
        deadline: float | None = getattr(_deadline, "at", None)
        if deadline is not None and time.monotonic() > deadline:
            raise CallTimeout(reason)
        super().consume_gas(amount, reason)


class SnapshotChain(DevChain):
    """The development chain's rules with the bounded computation, for reads only."""

    vm_configuration = ConsensusApplier(NoProofConsensus).amend_vm_configuration(
        (
            (
                0,
                PragueVM.configure(
                    _state_class=PragueState.configure(computation_class=BoundedComputation)
                ),
            ),
        )
    )


class SnapshotCalls:
    """Runs calls against the store at ``path`` with one read-only chain per worker thread."""

    def __init__(self, path: Path, limits: CallLimits) -> None:
        self.path = path
        self.limits = limits
        self._local = threading.local()
        self._opened: list[DurableAtomicDB] = []
        self._opened_lock = threading.Lock()

    def run(self, header: BlockHeaderAPI, work: Callable[[SnapshotChain], T]) -> T:
        """``work(chain)`` with this thread's deadline set; ``CallTimeout`` when it runs out."""
        chain = self._chain()
        _deadline.at = time.monotonic() + self.limits.timeout_s
        try:
            return work(chain)
        finally:
            _deadline.at = None

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
