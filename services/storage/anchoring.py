"""Epochs: the heads of every template log, cut at most every 2 s, anchored on chain in order.

Two threads keep the chain's transaction rate out of the write path. The *cutter* closes an
epoch every ``ROBOCLOUD_STORAGE_EPOCH_S`` seconds, or sooner once
``ROBOCLOUD_STORAGE_EPOCH_RECORDS`` records arrived (``notify``), when any log grew: it
computes the heads, builds the TMT and commits the epoch to ``epochs.sqlite`` (fsynced), so
an epoch's content is fixed before anything leaves the node. The *anchorer* takes the cut
epochs strictly in order: it stores the manifest in cas, then calls
``AnchorLog.anchor(epoch, tmtRoot, recordCount)`` with the node's key, and records the
transaction. A failure (ledger or cas unreachable, role not yet granted) stops it at that
epoch and retries with backoff, so epochs are never skipped; the cutter goes on meanwhile,
and the backlog is anchored one by one when the chain returns.

Never twice: before sending, the anchorer asks the chain for the node's root at that epoch.
A crash after the transaction was mined but before it was recorded finds the root there and
records it instead of sending again; a different root there is a conflict that stops
anchoring (``AnchorConflict``) rather than papering over it. Behind an external node the
transaction can still be pending when the node dies, where ``anchorAt`` does not see it: so
the signed transaction is saved with the epoch (``anchor_tx``) before it is sent, and the
restarted anchorer sends those same bytes again and waits for their receipt
(``Ledger.anchored_by``), signing a new anchor only once that nonce went to another mined
transaction. Signing a new one at once made the node's next nonce carry a second anchor of the
epoch, which reverted ("AnchorLog: epoch not increasing") once the first was mined, or, where
the node estimates gas on its pending block (anvil), refused every attempt until it was.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

from robocloud import jcs
from robocloud.ledger import Anchor, Ledger, SignedTransaction
from robocloud.proofs import AnchorRef, RecordId
from services.common.durable import open_sqlite, write_transaction
from services.storage.identity import NodeIdentity, Standing
from services.storage.recordlog import RecordLogs
from services.storage.tmt import EpochTree, TemplateHead, heads_from

log = logging.getLogger("robocloud.storage.anchoring")

MAX_RETRY_S = 30.0
TREE_CACHE = 64
"""Epoch trees kept in memory for proofs: the recent ones, which most proofs ask for."""

SCHEMA = """
CREATE TABLE IF NOT EXISTS epochs (
    epoch INTEGER PRIMARY KEY,
    heads TEXT NOT NULL,
    tmt_root BLOB NOT NULL,
    record_count INTEGER NOT NULL,
    cut_at REAL NOT NULL,
    manifest_cid TEXT,
    chain_id INTEGER,
    contract TEXT,
    tx TEXT,
    block INTEGER,
    anchor_tx TEXT
);
CREATE TABLE IF NOT EXISTS growth (
    template TEXT NOT NULL,
    size INTEGER NOT NULL,
    epoch INTEGER NOT NULL,
    PRIMARY KEY (template, size)
) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS epochs_pending ON epochs (epoch) WHERE tx IS NULL;
"""
"""``growth`` holds one row per template per epoch it grew in: the first epoch holding a
record is the one with the smallest size above the record's index. ``epochs_pending`` holds
the epochs not anchored yet, which the anchorer asks for before every anchor: a scan of every
epoch ever cut took 251 ms at 500,000 (11.6 days of 2 s epochs), and grew without end.
``anchor_tx`` is the signed anchor transaction of a pending epoch
(``SignedTransaction.to_json``), saved before it is sent and cleared once the epoch is
recorded anchored; a database from before it gets the column when opened."""


class NotAnchored(Exception):
    """The record exists, but no anchored epoch holds it yet: ``epoch`` is the one that will."""

    def __init__(self, record_id: RecordId, epoch: int) -> None:
        super().__init__(f"record {record_id} is not anchored yet; it will be in epoch {epoch}")
        self.record_id = record_id
        self.epoch = epoch


class RecordNotFound(Exception):
    def __init__(self, record_id: RecordId, size: int) -> None:
        super().__init__(f"no record {record_id}: {record_id.template} holds {size} records")
        self.record_id = record_id


class EpochNotFound(Exception):
    def __init__(self, epoch: int, last: int) -> None:
        super().__init__(f"no epoch {epoch}: the last epoch is {last}")
        self.epoch = epoch


class TemplateNotFound(Exception):
    def __init__(self, template: str) -> None:
        super().__init__(f"no records of template {template}")
        self.template = template


class InvalidConsistencyRange(Exception):
    """``first``/``second`` outside ``0 <= first <= second <= size``: ``field`` names which."""

    def __init__(self, field: str, value: int, message: str) -> None:
        super().__init__(f"{field}={value}: {message}")
        self.field = field
        self.value = value


class AnchorConflict(Exception):
    """The chain holds another root for one of this node's epochs: anchoring must stop."""


class NotYetAnchoring(Exception):
    """The node cannot anchor yet (unregistered, pending, or without the role)."""


@dataclass(frozen=True)
class Epoch:
    tree: EpochTree
    cut_at: float
    manifest_cid: str | None
    anchor: AnchorRef | None


MAX_SQLITE_INTEGER = 2**63 - 1
"""SQLite's integers are 64-bit: a larger epoch (``GET /v1/epochs/{epoch}`` takes up to
10**19 - 1) names none, where binding it raised OverflowError (a 500)."""


class EpochStore:
    """The node's epochs in SQLite (synchronous=FULL): each committed before it is anchored."""

    def __init__(self, path: Path, node: str) -> None:
        self._db = open_sqlite(path, SCHEMA, synchronous="FULL")
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(epochs)")}
        if "anchor_tx" not in columns:
            self._db.execute("ALTER TABLE epochs ADD COLUMN anchor_tx TEXT")
        self._node = node
        self._lock = threading.Lock()
        self._trees: OrderedDict[int, EpochTree] = OrderedDict()

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def last(self) -> int:
        with self._lock:
            row = self._db.execute("SELECT MAX(epoch) FROM epochs").fetchone()
        return int(row[0] or 0)

    def last_anchored(self) -> int:
        with self._lock:
            row = self._db.execute("SELECT MAX(epoch) FROM epochs WHERE tx IS NOT NULL").fetchone()
        return int(row[0] or 0)

    def tree(self, epoch: int) -> EpochTree | None:
        if not 0 <= epoch <= MAX_SQLITE_INTEGER:
            return None
        with self._lock:
            cached = self._trees.get(epoch)
            if cached is not None:
                self._trees.move_to_end(epoch)
                return cached
            row = self._db.execute("SELECT heads FROM epochs WHERE epoch = ?", (epoch,)).fetchone()
            if row is None:
                return None
            tree = EpochTree.build(epoch, heads_from(json.loads(row[0])))
            self._remember(tree)
            return tree

    def _remember(self, tree: EpochTree) -> None:
        self._trees[tree.epoch] = tree
        while len(self._trees) > TREE_CACHE:
            self._trees.popitem(last=False)

    def get(self, epoch: int) -> Epoch | None:
        tree = self.tree(epoch)
        if tree is None:
            return None
        with self._lock:
            cut_at, cid, chain_id, contract, node_tx, block = self._db.execute(
                "SELECT cut_at, manifest_cid, chain_id, contract, tx, block FROM epochs "
                "WHERE epoch = ?",
                (epoch,),
            ).fetchone()
        anchor = None
        if node_tx is not None:
            anchor = AnchorRef(chain_id, contract, self._node, epoch, node_tx, block)
        return Epoch(tree, cut_at, cid, anchor)

    def cut(self, heads: list[TemplateHead]) -> EpochTree | None:
        """Commit the next epoch when any head grew since the last; the new epoch's tree."""
        last = self.last()
        previous = self.tree(last) if last else None
        grown = [
            head
            for head in heads
            if previous is None
            or (known := previous.head(head.template)) is None
            or known.size < head.size
        ]
        if not grown:
            return None
        tree = EpochTree.build(last + 1, heads)
        described = json.dumps([head.describe() for head in tree.heads])
        with self._lock:
            with write_transaction(self._db):
                self._db.execute(
                    "INSERT INTO epochs (epoch, heads, tmt_root, record_count, cut_at) "
                    "VALUES (?, ?, ?, ?, ?)",
                    (tree.epoch, described, tree.root, tree.record_count, time.time()),
                )
                self._db.executemany(
                    "INSERT INTO growth (template, size, epoch) VALUES (?, ?, ?)",
                    [(head.template, head.size, tree.epoch) for head in grown],
                )
            self._remember(tree)
        return tree

    def epoch_of(self, template: str, index: int) -> int | None:
        """The first epoch holding record ``index`` of ``template``, if one was cut."""
        with self._lock:
            row = self._db.execute(
                "SELECT epoch FROM growth WHERE template = ? AND size > ? ORDER BY size LIMIT 1",
                (template, index),
            ).fetchone()
        return None if row is None else int(row[0])

    def pending(self) -> list[int]:
        with self._lock:
            rows = self._db.execute(
                "SELECT epoch FROM epochs WHERE tx IS NULL ORDER BY epoch"
            ).fetchall()
        return [int(row[0]) for row in rows]

    def set_manifest_cid(self, epoch: int, cid: str) -> None:
        with self._lock:
            self._db.execute("UPDATE epochs SET manifest_cid = ? WHERE epoch = ?", (cid, epoch))

    def set_anchored(self, epoch: int, chain_id: int, contract: str, tx: str, block: int) -> None:
        with self._lock:
            self._db.execute(
                "UPDATE epochs SET chain_id = ?, contract = ?, tx = ?, block = ?, "
                "anchor_tx = NULL WHERE epoch = ?",
                (chain_id, contract, tx, block, epoch),
            )

    def anchor_tx(self, epoch: int) -> SignedTransaction | None:
        """The anchor transaction signed for ``epoch`` and saved before it was sent."""
        with self._lock:
            row = self._db.execute(
                "SELECT anchor_tx FROM epochs WHERE epoch = ?", (epoch,)
            ).fetchone()
        if row is None or row[0] is None:
            return None
        return SignedTransaction.from_json(json.loads(row[0]))

    def set_anchor_tx(self, epoch: int, signed: SignedTransaction) -> None:
        """Save (fsynced) the anchor transaction of ``epoch`` before it is sent."""
        with self._lock:
            self._db.execute(
                "UPDATE epochs SET anchor_tx = ? WHERE epoch = ?",
                (json.dumps(signed.to_json()), epoch),
            )


@dataclass
class LedgerAndCas:
    """The node's clients of the ledger and the cas, signing as the node."""

    ledger: Ledger
    cas: ManifestStore

    def close(self) -> None:
        self.ledger.close()
        closer = getattr(self.cas, "close", None)
        if closer is not None:
            closer()


class ManifestStore(Protocol):
    """Where manifests go before their root goes on chain (the cas; an SDK ``Cas``)."""

    def add_bytes(self, data: bytes) -> Any: ...


class Chain(Protocol):
    """What the anchorer needs from a connection to the chain and the cas."""

    ledger: Ledger
    cas: ManifestStore

    def close(self) -> None: ...


class Anchorer:
    """The cutter and anchorer threads of one storage node; ``notify`` after every append."""

    def __init__(
        self,
        logs: RecordLogs,
        epochs: EpochStore,
        node: NodeIdentity,
        connect: Callable[[], Chain],
        *,
        epoch_s: float,
        epoch_records: int,
        retry_s: float,
        register: bool,
    ) -> None:
        self.logs = logs
        self.epochs = epochs
        self.node = node
        self._connect = connect
        self._epoch_s = epoch_s
        self._epoch_records = epoch_records
        self._retry_s = retry_s
        self._register = register
        self._stop = threading.Event()
        self._cut_now = threading.Event()
        self._cut_done = threading.Event()
        self._since_cut = 0
        self._count_lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self._chain: Chain | None = None
        self.standing: Standing | None = None
        self.last_error: str | None = None
        self.conflict: str | None = None

    def notify(self, count: int) -> None:
        """``count`` records were appended: end the epoch early once enough arrived."""
        with self._count_lock:
            self._since_cut += count
            if self._since_cut >= self._epoch_records:
                self._cut_now.set()

    def start(self) -> None:
        """Start cutting and anchoring; the anchorer's first round, which gets the node its
        standing, runs at once rather than after the first cut."""
        self._cut_done.set()
        for name, target in (("epoch-cutter", self._cut_loop), ("anchorer", self._anchor_loop)):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        self._stop.set()
        self._cut_now.set()
        self._cut_done.set()
        for thread in self._threads:
            thread.join()
        if self._chain is not None:
            self._chain.close()

    def cut(self) -> EpochTree | None:
        """Close an epoch now if any log grew (the cutter's step, also for tests and shutdown)."""
        with self._count_lock:
            self._since_cut = 0
            self._cut_now.clear()
        heads = [
            TemplateHead(template, size, self.logs.root(template, size))
            for template, size in self.logs.sizes().items()
            if size > 0
        ]
        tree = self.epochs.cut(heads)
        if tree is not None:
            self._cut_done.set()
        return tree

    def _cut_loop(self) -> None:
        while not self._stop.is_set():
            self._cut_now.wait(self._epoch_s)
            if self._stop.is_set():
                return
            try:
                self.cut()
            except Exception:
                log.exception("cutting an epoch failed")
                self._stop.wait(self._retry_s)

    def _anchor_loop(self) -> None:
        failures = 0
        while not self._stop.is_set():
            self._cut_done.wait(self._epoch_s)
            self._cut_done.clear()
            try:
                while not self._stop.is_set() and self.anchor_next():
                    pass
                failures = 0
                self.last_error = None
            except AnchorConflict as exc:
                self.conflict = str(exc)
                log.error("anchoring stopped", extra={"reason": str(exc)})
                return
            except Exception as exc:
                error = f"{type(exc).__name__}: {exc}"
                waiting_for_role = isinstance(exc, NotYetAnchoring)
                if error != self.last_error:
                    _log_failed_round(error, waiting_for_role)
                self.last_error = error
                if not waiting_for_role:
                    self._drop_chain()
                self._stop.wait(retry_wait(self._retry_s, failures, exc))
                failures = 0 if waiting_for_role else failures + 1
                self._cut_done.set()

    def _drop_chain(self) -> None:
        if self._chain is not None:
            self._chain.close()
            self._chain = None

    def _chain_now(self) -> Chain:
        if self._chain is None:
            self._chain = self._connect()
        return self._chain

    def anchor_next(self) -> bool:
        """Anchor the oldest pending epoch; whether there was one. Raises to retry later.

        The node's standing comes first, with nothing to anchor too: a new node registers at
        start, not at its first anchor. Until it is registered, cas (``ROBOCLOUD_AUTH=
        registered``) refused its writes, so the first dataset an ingest published, and any
        large value it offloaded, failed; and the ledger's granter, waiting for the node to
        register, asked for its address every second for as long as the node stayed idle.
        """
        chain = self._chain_now()
        self._ensure_standing(chain.ledger)
        pending = self.epochs.pending()
        if not pending:
            return False
        epoch = pending[0]
        record = self.epochs.get(epoch)
        assert record is not None
        tree = record.tree
        if record.manifest_cid is None:
            manifest = jcs.canonical(tree.manifest(self.node.address))
            cid = str(chain.cas.add_bytes(manifest))
            self.epochs.set_manifest_cid(epoch, cid)
        ledger = chain.ledger
        existing = ledger.anchor_at(self.node.address, epoch)
        if existing is not None:
            if existing.root != tree.root:
                raise AnchorConflict(
                    f"AnchorLog holds {existing.root.hex()} for epoch {epoch}, "
                    f"this node cut {tree.root.hex()}"
                )
            tx = self._recorded_tx(ledger, existing)
            anchored = existing.block_number
        else:
            result = self._sent_before(ledger, epoch, tree) or ledger.anchor(
                epoch,
                tree.root,
                tree.record_count,
                before_send=lambda signed: self.epochs.set_anchor_tx(epoch, signed),
            )
            assert result.tx_hash is not None
            tx, anchored = result.tx_hash, result.block_number
        self.epochs.set_anchored(epoch, ledger.chain_id, ledger.addresses.anchor_log, tx, anchored)
        self.last_error = None
        log.info("anchored", extra={"epoch": epoch, "tx": tx, "records": tree.record_count})
        return True

    def _sent_before(self, ledger: Ledger, epoch: int, tree: EpochTree) -> Anchor | None:
        """The anchor made by the transaction saved for ``epoch`` before an earlier attempt
        sent it, once mined: sent again and waited for, since behind an external node it may
        still be pending (``anchorAt`` does not see it), and replaced at a higher price (saved
        first) once it has waited past the receipt timeout. None when none was saved, or it
        reverted or its nonce went to another transaction, so it anchored nothing: a
        transaction it replaced may have anchored the epoch, which ``anchorAt`` then shows at
        the next attempt, and AnchorLog refuses a second anchor of an epoch."""
        signed = self.epochs.anchor_tx(epoch)
        if signed is None:
            return None
        return ledger.anchored_by(
            signed,
            epoch,
            tree.root,
            tree.record_count,
            before_send=lambda replacement: self.epochs.set_anchor_tx(epoch, replacement),
        )

    def _recorded_tx(self, ledger: Ledger, existing: Anchor) -> str:
        """The transaction of the ``Anchored`` event that is ``existing``, this node's anchor
        as ``anchorAt`` holds it: same node, epoch, root, count, time and block. A node's
        ``eth_getLogs`` answered another node's anchor, of another epoch and block, which
        was recorded as this node's; an event that is not the anchor itself is never taken."""
        found = ledger.anchors(
            node=existing.node,
            epoch=existing.epoch,
            from_block=existing.block_number,
            to_block=existing.block_number,
        )
        for anchor in found:
            if anchor.tx_hash and replace(anchor, tx_hash=None) == existing:
                return anchor.tx_hash
        raise AnchorConflict(
            f"epoch {existing.epoch} is anchored, but no Anchored event of this node shows it"
        )

    def _ensure_standing(self, ledger: Ledger) -> None:
        if self.standing is Standing.ANCHORING:
            return
        if self._register:
            self.standing = self.node.ensure_registered(ledger)
        else:
            self.standing = self.node.standing(ledger)
        if self.standing is not Standing.ANCHORING:
            raise NotYetAnchoring(
                f"the node {self.node.address} is {self.standing.value} and lacks the "
                "storage_node role; grant it with `robocloud admin grant "
                f"{self.node.address} storage_node`"
            )


def _log_failed_round(error: str, waiting_for_role: bool) -> None:
    """Once per distinct error. A new node waits for its role at every first start (under
    ``make up`` for about a second, until the ledger's granter sees it), so that is said at
    info, not as a failure."""
    if waiting_for_role:
        log.info("waiting for the storage_node role", extra={"reason": error})
    else:
        log.warning("anchoring failed; retrying", extra={"error": error})


def retry_wait(base: float, failures: int, error: Exception) -> float:
    """Seconds to wait before the next attempt after ``error``, which followed ``failures``
    failed attempts in a row.

    A peer that failed (the ledger or cas down, a transaction refused) is asked half as
    often each time, down to once every ``MAX_RETRY_S``. A node waiting for its role faces
    no failure but an admin's action, which a deployment's granter takes within a second of
    seeing the node: asking the chain again every ``base`` seconds (three view calls) anchors
    the first epoch right after the grant, where the doubling made it wait up to 30 s.
    """
    if isinstance(error, NotYetAnchoring):
        return base
    return float(min(base * 2**failures, MAX_RETRY_S))


class ProofService:
    """Proofs, consistency proofs and epochs, read from the logs and the epoch store."""

    def __init__(self, logs: RecordLogs, epochs: EpochStore, node: str) -> None:
        self.logs = logs
        self.epochs = epochs
        self.node = node

    def record_proof(self, record_id: RecordId) -> dict[str, Any]:
        template = record_id.template
        size = self.logs.size(template)
        if record_id.index >= size:
            raise RecordNotFound(record_id, size)
        epoch = self.epochs.epoch_of(template, record_id.index)
        if epoch is None:
            raise NotAnchored(record_id, self.epochs.last() + 1)
        record = self.epochs.get(epoch)
        assert record is not None
        if record.anchor is None:
            raise NotAnchored(record_id, epoch)
        head = record.tree.head(template)
        assert head is not None
        entry = self.logs.entry(template, record_id.index)
        tmt_index, tmt_inclusion = record.tree.inclusion(template)
        inclusion = self.logs.inclusion_proof(template, record_id.index, head.size)
        return {
            "id": str(record_id),
            "record": json.loads(entry.record),
            "leaf_index": record_id.index,
            "tree_size": head.size,
            "template_root": head.root.hex(),
            "inclusion": [node.hex() for node in inclusion],
            "epoch": epoch,
            "tmt_leaf_index": tmt_index,
            "tmt_size": len(record.tree.heads),
            "tmt_inclusion": [node.hex() for node in tmt_inclusion],
            "tmt_root": record.tree.root.hex(),
            "anchor": record.anchor.describe(),
        }

    def consistency(self, template: str, first: int, second: int) -> dict[str, Any]:
        size = self.logs.size(template)
        if size == 0:
            raise TemplateNotFound(template)
        if second > size:
            raise InvalidConsistencyRange("second", second, f"{template} holds {size} records")
        if first > second:
            raise InvalidConsistencyRange("first", first, f"must not exceed second={second}")
        return {
            "template": template,
            "first": first,
            "second": second,
            "first_root": self.logs.root(template, first).hex(),
            "second_root": self.logs.root(template, second).hex(),
            "proof": [node.hex() for node in self.logs.consistency_proof(template, first, second)],
        }

    def epoch(self, epoch: int) -> dict[str, Any]:
        record = self.epochs.get(epoch)
        if record is None:
            raise EpochNotFound(epoch, self.epochs.last())
        return {
            **record.tree.manifest(self.node),
            "manifest_cid": record.manifest_cid,
            "cut_at": record.cut_at,
            "status": "anchored" if record.anchor else "pending",
            "anchor": record.anchor.describe() if record.anchor else None,
        }


class StorageNode:
    """The node's record logs, epochs, identity and anchorer, opened and closed together.

    The record store calls ``notify(count)`` after each append; proofs read through
    ``proofs``. ``anchorer`` is None when anchoring is off (then no epoch is ever cut).
    """

    def __init__(
        self,
        data_dir: Path,
        identity: NodeIdentity,
        connect: Callable[[], Chain],
        *,
        anchor: bool,
        epoch_s: float,
        epoch_records: int,
        retry_s: float,
        register: bool,
    ) -> None:
        self.identity = identity
        self.logs = RecordLogs(data_dir / "logs")
        self.epochs = EpochStore(data_dir / "epochs.sqlite", identity.address)
        self.proofs = ProofService(self.logs, self.epochs, identity.address)
        self.anchorer = (
            Anchorer(
                self.logs,
                self.epochs,
                identity,
                connect,
                epoch_s=epoch_s,
                epoch_records=epoch_records,
                retry_s=retry_s,
                register=register,
            )
            if anchor
            else None
        )

    def notify(self, count: int) -> None:
        if self.anchorer is not None:
            self.anchorer.notify(count)

    def start(self) -> None:
        if self.anchorer is not None:
            self.anchorer.start()

    def close(self) -> None:
        if self.anchorer is not None:
            self.anchorer.stop()
        self.epochs.close()
        self.logs.close()

    def describe(self) -> dict[str, Any]:
        """What ``GET /v1/node`` publishes: the address the ledger grants the role to."""
        anchorer = self.anchorer
        return {
            "address": self.identity.address,
            "anchoring": anchorer is not None,
            "standing": anchorer.standing.value if anchorer and anchorer.standing else None,
            "last_epoch": self.epochs.last(),
            "last_anchored_epoch": self.epochs.last_anchored(),
            "anchor_error": anchorer.conflict or anchorer.last_error if anchorer else None,
        }
