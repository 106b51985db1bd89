"""The development chain's state on disk: py-evm's key-value database in SQLite.

eth-tester keeps its chain in an in-memory ``AtomicDB``; replaying a journal of transactions
to rebuild it grows with the chain's history (ENVIRONMENT.md measured over 20 minutes for
100,000 transactions). Instead py-evm writes its trie nodes, headers and receipts straight
into this store: a restart reopens the database and the canonical head is where it was, with
the same hash, in constant time.

Each of py-evm's atomic batches (a mined block, a persisted state) is one SQLite transaction
with ``synchronous=FULL``, so a kill -9 loses at most a batch that was never acknowledged; and
a batch whose COMMIT failed is never found by a restart either (see ``SqliteKeyValue``).
The chain itself is a py-evm ``MiningChain`` with chain id 1337 and eth-tester's funded
genesis, like eth-tester's own tester chain but with a durable database underneath.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, cast

from eth.abc import (
    AtomicWriteBatchAPI,
    BlockAPI,
    BlockHeaderAPI,
    ReceiptAPI,
    SignedTransactionAPI,
    VirtualMachineAPI,
)
from eth.chains.base import MiningChain
from eth.consensus.applier import ConsensusApplier
from eth.consensus.noproof import NoProofConsensus
from eth.db.atomic import AtomicDB
from eth.db.backends.base import BaseDB
from eth.exceptions import CanonicalHeadNotFound
from eth.typing import AccountState
from eth.vm.forks.prague import PragueVM
from eth_tester.backends.pyevm.main import (
    generate_genesis_state_for_keys,
    get_default_account_keys,
    get_default_genesis_params,
)

from services.common.durable import FAILED_COMMIT_SCHEMA, open_sqlite, write_transaction
from services.ledger.precompile_budget import BudgetedState

CHAIN_ID = 1337
GENESIS_TIMESTAMP = 0
"""As Ethereum mainnet's genesis; every later block is stamped with the time it is mined."""


KV_SCHEMA = "CREATE TABLE IF NOT EXISTS kv (key BLOB PRIMARY KEY, value BLOB NOT NULL)"
SCHEMA = f"{KV_SCHEMA};{FAILED_COMMIT_SCHEMA}"
"""The key-value table, and ``failed_commit``: writing it voids a failed COMMIT's frames."""


class SqliteKeyValue(BaseDB):
    """A durable byte-to-byte map; writes outside a transaction commit one by one.

    A transaction is acknowledged only when its COMMIT succeeds. One that fails (its fsync
    of the write-ahead log refused by the disk) is rolled back in this process, but its
    frames, commit marker included, may already be in the log's file past the last frame
    SQLite counts: a restart's WAL recovery read them and brought back the block, while the
    ledger had answered its transaction as failed. So a failed COMMIT is followed at once by
    a small commit written over those frames (``void_failed_commit``).
    """

    def __init__(self, path: Path, *, read_only: bool = False) -> None:
        self.depth = 0
        self.connection = open_sqlite(path, SCHEMA, synchronous="FULL")
        if read_only:
            self.connection.execute("PRAGMA query_only=ON")

    def __getitem__(self, key: bytes) -> bytes:
        row = self.connection.execute("SELECT value FROM kv WHERE key = ?", (key,)).fetchone()
        if row is None:
            raise KeyError(key)
        return bytes(row[0])

    def __setitem__(self, key: bytes, value: bytes) -> None:
        self.connection.execute("INSERT OR REPLACE INTO kv VALUES (?, ?)", (key, value))

    def __delitem__(self, key: bytes) -> None:
        if self.connection.execute("DELETE FROM kv WHERE key = ?", (key,)).rowcount == 0:
            raise KeyError(key)

    def _exists(self, key: bytes) -> bool:
        return (
            self.connection.execute("SELECT 1 FROM kv WHERE key = ?", (key,)).fetchone() is not None
        )

    @contextmanager
    def transaction(self) -> Iterator[None]:
        """One SQLite transaction; nested calls join the outermost, which alone commits.

        Mining a block writes two py-evm batches (state, then block); running both inside
        one outer transaction makes the block atomic and costs one fsync instead of two.
        """
        if self.depth:
            self.depth += 1
            try:
                yield
            finally:
                self.depth -= 1
            return
        self.depth = 1
        try:
            with write_transaction(self.connection):
                yield
        finally:
            self.depth = 0

    def close(self) -> None:
        self.connection.close()


class DurableAtomicDB(AtomicDB):
    """py-evm's atomic database whose every batch is one SQLite transaction."""

    def __init__(self, path: Path, *, read_only: bool = False) -> None:
        self.store = SqliteKeyValue(path, read_only=read_only)
        super().__init__(self.store)

    @contextmanager
    def atomic_batch(self) -> Iterator[AtomicWriteBatchAPI]:
        with self.store.transaction(), super().atomic_batch() as batch:
            yield batch

    def close(self) -> None:
        self.store.close()


class DevChain(MiningChain):
    """Chain id 1337, no proof of work, the newest fork eth-tester supports."""

    chain_id = CHAIN_ID
    vm_configuration = ConsensusApplier(NoProofConsensus).amend_vm_configuration(
        ((0, PragueVM.configure(_state_class=BudgetedState)),)
    )

    def create_header_from_parent(
        self, parent_header: BlockHeaderAPI, **header_params: Any
    ) -> BlockHeaderAPI:
        """Keep the genesis gas limit, as eth-tester does, instead of py-evm's drift."""
        header_params["gas_limit"] = parent_header.gas_limit
        return super().create_header_from_parent(parent_header, **header_params)

    def next_vm(self, timestamp: int, mix_hash: bytes) -> VirtualMachineAPI:
        """The VM that will mine the next block, its header given the time and randomness;
        its state is the head's, so checks read what the block will be built on."""
        self.header = self.header.copy(timestamp=timestamp, mix_hash=mix_hash)
        return self.get_vm(self.header)

    def mine_one(
        self, vm: VirtualMachineAPI, transaction: SignedTransactionAPI
    ) -> tuple[BlockAPI, tuple[ReceiptAPI, ...]]:
        """Mine ``transaction`` alone in a block on ``vm`` (from ``next_vm``) and store it.

        This is py-evm's ``mine_all`` less what only a block received from elsewhere needs:
        ``mine_all`` validates the block it has just built twice (``VM.mine_block`` and
        ``Chain.persist_block``: its roots, gas and header fields against what it computed
        itself a moment before) and reads it back from the database to report it as the new
        canonical block. The block, its receipts and what is stored are the same.
        """
        header = vm.get_header()
        new_header, receipts, _ = vm.apply_all_transactions([transaction], header)
        filled = vm.set_block_transactions_and_withdrawals(
            vm.get_block(), new_header, [transaction], receipts
        )
        block = vm.finalize_block(filled).block
        self.chaindb.persist_block(block)
        self.header = self.create_header_from_parent(block.header)
        return block, receipts


def default_genesis_state(funded_accounts: int = 10) -> dict[bytes, Any]:
    """eth-tester's well-known funded test keys: for unit tests, never for the service."""
    state: dict[bytes, Any] = generate_genesis_state_for_keys(
        get_default_account_keys(funded_accounts)
    )
    return state


def open_chain(
    path: Path, genesis_state: Mapping[bytes, Any] | None = None
) -> tuple[DevChain, DurableAtomicDB]:
    """Reopen the chain stored at ``path``, or create it with ``genesis_state``.

    The canonical head is written last when a genesis is persisted, so a store without one
    (new, or cut short by a crash) simply gets the same genesis again: the genesis depends on
    ``genesis_state`` alone (its time is ``GENESIS_TIMESTAMP``, not eth-tester's clock, which
    gave two chains created a second apart two genesis hashes). ``genesis_state`` maps
    canonical addresses to eth-tester account states (balance, nonce, code, storage).
    """
    db = DurableAtomicDB(path)
    try:
        return DevChain(db), db
    except CanonicalHeadNotFound:
        pass
    state = dict(genesis_state) if genesis_state is not None else default_genesis_state()
    params = get_default_genesis_params({"timestamp": GENESIS_TIMESTAMP})
    chain = DevChain.from_genesis(db, params, cast(AccountState, state))
    return cast(DevChain, chain), db
