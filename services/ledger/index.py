"""The event index: every log the chain emitted, and the contracts' state as events tell it.

eth-tester's ``get_logs`` scans every block and grows quadratically with the number of events
(ENVIRONMENT.md), so ``eth_getLogs`` and the REST reads are served from this SQLite index
instead. It is fed one block at a time, in order, from receipts (embedded chain) or from
``eth_getLogs`` pages (external node). Each block is one SQLite transaction that also moves
the index's cursor, so after a crash the index is exactly the blocks up to its cursor and
catching up from the chain repeats nothing.

Only events emitted by the deployed Registry and AnchorLog update the robot, advertisement
and anchor tables: anybody may deploy a contract that emits a look-alike ``RobotRegistered``,
and such a log must never make its sender look registered.

The index is fed in order and cannot skip a block, so no event may make a block unindexable:
uint64 values a caller chooses (an anchor's epoch and record count) are stored biased by
-2^63 to fit SQLite's signed 64-bit integers with their order kept, and an event whose
projection fails all the same is logged and left out of the tables (its log is still
indexed) instead of failing its block, and with it every later one, forever.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from robocloud.ledger.abi import ContractAbi, DecodedLog
from services.common.changes import Changes
from services.common.durable import open_sqlite, write_transaction
from services.ledger.encoding import MAX_SQLITE_INTEGER, LogEntry

log = logging.getLogger("robocloud.ledger.index")

MAX_LOG_RESULTS = 10_000
"""``eth_getLogs`` answers at most this many logs; a wider query is refused (as Infura does)."""
LOG_QUERY_BUDGET_S = 5.0
"""How long one log query may run in SQLite before it is stopped and refused. Every topic
position and the address have an index, so a query reads about what it answers; what is left
is a query the planner misjudges (two common topics, say) over a long chain."""
QUERY_PROGRESS_STEPS = 10_000
"""SQLite instructions between two looks at a query's clock (tens of microseconds)."""

SCHEMA = """
CREATE TABLE IF NOT EXISTS cursor (
    id INTEGER PRIMARY KEY CHECK (id = 0), block_number INTEGER NOT NULL, block_hash BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS logs (
    block_number INTEGER NOT NULL, log_index INTEGER NOT NULL, block_hash BLOB NOT NULL,
    tx_hash BLOB NOT NULL, tx_index INTEGER NOT NULL, address BLOB NOT NULL,
    topic0 BLOB, topic1 BLOB, topic2 BLOB, topic3 BLOB, data BLOB NOT NULL,
    PRIMARY KEY (block_number, log_index)
) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS logs_address ON logs (address, topic0, block_number);
CREATE INDEX IF NOT EXISTS logs_topic0 ON logs (topic0, block_number);
CREATE INDEX IF NOT EXISTS logs_topic1 ON logs (topic1, block_number);
CREATE INDEX IF NOT EXISTS logs_topic2 ON logs (topic2, block_number);
CREATE INDEX IF NOT EXISTS logs_topic3 ON logs (topic3, block_number);
CREATE TABLE IF NOT EXISTS robots (
    address TEXT PRIMARY KEY, metadata_cid BLOB NOT NULL, registered_at INTEGER NOT NULL,
    registered_block INTEGER NOT NULL, active INTEGER NOT NULL, suspended INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS registrations (
    address TEXT PRIMARY KEY, metadata_cid BLOB NOT NULL, requested_at INTEGER NOT NULL,
    requested_block INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS registrations_block ON registrations (requested_block);
CREATE TABLE IF NOT EXISTS roles (
    address TEXT NOT NULL, role BLOB NOT NULL, PRIMARY KEY (address, role)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS advertisements (
    block_number INTEGER NOT NULL, log_index INTEGER NOT NULL, cid BLOB NOT NULL,
    advertiser TEXT NOT NULL, description_cid BLOB NOT NULL, first INTEGER NOT NULL,
    timestamp INTEGER NOT NULL, tx_hash BLOB NOT NULL, PRIMARY KEY (block_number, log_index)
) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS advertisements_cid ON advertisements (cid, block_number);
CREATE INDEX IF NOT EXISTS advertisements_advertiser ON advertisements (advertiser, block_number);
CREATE TABLE IF NOT EXISTS anchors (
    node TEXT NOT NULL, epoch INTEGER NOT NULL, root BLOB NOT NULL, record_count INTEGER NOT NULL,
    timestamp INTEGER NOT NULL, block_number INTEGER NOT NULL, tx_hash BLOB NOT NULL,
    PRIMARY KEY (node, epoch)
) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS anchors_epoch ON anchors (epoch);
CREATE INDEX IF NOT EXISTS anchors_block ON anchors (block_number, node);
CREATE INDEX IF NOT EXISTS anchors_node_block ON anchors (node, block_number);
"""
"""``anchors.epoch`` and ``anchors.record_count`` hold ``biased`` values."""

VERSION = 1
"""``PRAGMA user_version`` of an index in this schema; ``MIGRATIONS[v]`` takes version v to
v + 1 in place, so that an index written by an older ledger (or wedged by an event it could
not store) is carried on from its cursor instead of being rebuilt from block 0."""
MIGRATIONS = {
    # Version 0 stored epochs and record counts as they are; each was below 2^63 (larger
    # ones could not be stored), so subtracting 2^63 (in two steps: the literal 2^63 is not
    # an SQLite integer) cannot overflow.
    0: "UPDATE anchors SET epoch = epoch - 9223372036854775807 - 1, "
    "record_count = record_count - 9223372036854775807 - 1",
}
UINT64_BIAS = 2**63


def biased(value: int) -> int:
    """A uint64 as an SQLite integer: ``value - 2^63``, which fits and keeps the order."""
    return value - UINT64_BIAS


def unbiased(value: int) -> int:
    return value + UINT64_BIAS


@dataclass(frozen=True)
class LogFilter:
    """``eth_getLogs`` criteria: any of ``addresses``; per position, any of the topics."""

    from_block: int
    to_block: int
    addresses: tuple[bytes, ...] = ()
    topics: tuple[tuple[bytes, ...] | None, ...] = ()
    block_hash: bytes | None = None


MAX_WAITERS = 256
"""Reads waiting at once for a new block (``wait_s``); beyond, a read answers at once."""


class IndexLimitError(Exception):
    """A query matched more logs than one answer may hold, or ran past its time."""


class EventIndex:
    """SQLite-backed log index and contract-state projection."""

    def __init__(self, path: Path, registry: str, anchor_log: str) -> None:
        self.changes = Changes(MAX_WAITERS)
        """Advanced by each block indexed or rewound: what a read of new events waits on."""
        self._lock = threading.Lock()
        self._db = open_sqlite(path, SCHEMA, synchronous="NORMAL")
        self._migrate()
        self._reader_lock = threading.Lock()
        self._reader = sqlite3.connect(
            f"{path.absolute().as_uri()}?mode=ro", uri=True, check_same_thread=False
        )
        """Log queries read here, a snapshot of their own (WAL): on the writer's connection
        they held its lock, so the block being mined waited behind any query a stranger sent."""
        self.registry = ContractAbi.load("Registry")
        self.anchor_log = ContractAbi.load("AnchorLog")
        self._contracts = {
            bytes.fromhex(registry[2:]): self.registry,
            bytes.fromhex(anchor_log[2:]): self.anchor_log,
        }

    def close(self) -> None:
        self.changes.close()
        with self._reader_lock:
            self._reader.close()
        with self._lock:
            self._db.close()

    def _migrate(self) -> None:
        """Bring an index written by an older ledger to ``VERSION``, one transaction a step."""
        version = int(self._db.execute("PRAGMA user_version").fetchone()[0])
        if version > VERSION:
            raise RuntimeError(
                f"the event index {version} is newer than this ledger's ({VERSION}); "
                "delete index.sqlite to rebuild it from the chain"
            )
        while version < VERSION:
            with self._transaction():
                self._db.execute(MIGRATIONS[version])
                self._db.execute(f"PRAGMA user_version = {version + 1}")
            log.info("event index migrated", extra={"version": version + 1})
            version += 1

    # ----- feeding -----

    def cursor(self) -> tuple[int, bytes] | None:
        """The last indexed block's number and hash; None before the first block."""
        with self._lock:
            row = self._db.execute("SELECT block_number, block_hash FROM cursor").fetchone()
        return (int(row[0]), bytes(row[1])) if row else None

    def add_block(self, number: int, block_hash: bytes, logs: Iterable[LogEntry]) -> None:
        """Index one block's logs and advance the cursor to it, all in one transaction."""
        with self._transaction():
            for entry in logs:
                self._insert(entry)
            self._db.execute("INSERT OR REPLACE INTO cursor VALUES (0, ?, ?)", (number, block_hash))
        self.changes.advance()

    def rewind(self, to_block: int, block_hash: bytes) -> None:
        """Forget everything after block ``to_block`` (whose hash is ``block_hash``) when an
        external chain reorganised, and re-derive the state tables from the logs left."""
        with self._transaction():
            self._db.execute("DELETE FROM logs WHERE block_number > ?", (to_block,))
            for table in ("robots", "registrations", "roles", "advertisements", "anchors"):
                self._db.execute(f"DELETE FROM {table}")
            rows = self._db.execute("SELECT * FROM logs ORDER BY block_number, log_index")
            for row in rows.fetchall():
                self._apply(_entry(row))
            self._db.execute(
                "INSERT OR REPLACE INTO cursor VALUES (0, ?, ?)", (to_block, block_hash)
            )
        self.changes.advance()

    @contextmanager
    def _transaction(self) -> Iterator[None]:
        """One SQLite write transaction under the lock: committed whole, or rolled back."""
        with self._lock, write_transaction(self._db):
            yield

    def _insert(self, entry: LogEntry) -> None:
        topics = list(entry.topics) + [None] * (4 - len(entry.topics))
        self._db.execute(
            "INSERT OR IGNORE INTO logs VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (
                entry.block_number,
                entry.log_index,
                entry.block_hash,
                entry.tx_hash,
                entry.tx_index,
                entry.address,
                *topics[:4],
                entry.data,
            ),
        )
        self._apply(entry)

    def _apply(self, entry: LogEntry) -> None:
        """Project one of the contracts' events onto the state tables. A projection that
        fails is undone and logged: the block is indexed all the same, since a block left
        unindexed would stop every block after it (the index is fed in order)."""
        contract = self._contracts.get(entry.address)
        if contract is None:
            return
        self._db.execute("SAVEPOINT projection")
        try:
            decoded = contract.decode_log(entry.to_rpc())
            handler = _HANDLERS.get(decoded.event) if decoded is not None else None
            if decoded is not None and handler is not None:
                handler(self._db, decoded, entry)
        except Exception:
            self._db.execute("ROLLBACK TO projection")
            log.exception(
                "event not projected; its log is indexed",
                extra={"block": entry.block_number, "log_index": entry.log_index},
            )
        self._db.execute("RELEASE projection")

    # ----- queries -----

    def logs(self, query: LogFilter) -> list[LogEntry]:
        """Logs matching ``query`` in chain order; ``IndexLimitError`` past the limit, unless
        the query is one block: a block cannot be narrowed, so it is answered whole (its gas
        bounds its logs), as anvil and geth answer it."""
        if query.from_block == query.to_block:
            return self._select(query, None)
        found = self._select(query, MAX_LOG_RESULTS + 1)
        if len(found) > MAX_LOG_RESULTS:
            raise IndexLimitError(
                f"query returned more than {MAX_LOG_RESULTS} results; narrow the block range"
            )
        return found

    def logs_page(self, query: LogFilter) -> tuple[list[LogEntry], int]:
        """The logs of as many whole blocks from ``query.from_block`` on as fit in
        ``MAX_LOG_RESULTS``, and the last block they cover: what a filter poll answers, so
        that a filter moves on however many logs its blocks hold. The first block that holds
        any is answered whole even past the limit (as geth answers a poll whole)."""
        found = self._select(query, MAX_LOG_RESULTS + 1)
        if len(found) <= MAX_LOG_RESULTS:
            return found, query.to_block
        cut = found[MAX_LOG_RESULTS].block_number
        if cut > found[0].block_number:
            return [entry for entry in found if entry.block_number < cut], cut - 1
        alone = replace(query, from_block=cut, to_block=cut)
        return self._select(alone, None), cut

    def _select(self, query: LogFilter, limit: int | None) -> list[LogEntry]:
        """Logs matching ``query`` in chain order, at most ``limit`` (None: all)."""
        clauses = ["block_number BETWEEN ? AND ?"]
        params: list[Any] = [query.from_block, query.to_block]
        if query.block_hash is not None:
            clauses.append("block_hash = ?")
            params.append(query.block_hash)
        # A constraint on an indexed argument (topic1..3) is nearly always the selective one;
        # the unary + keeps SQLite from choosing the address/topic0 index over it instead.
        narrow = any(query.topics[1:4])
        prefix = "+" if narrow else ""
        if query.addresses:
            clauses.append(f"{prefix}address IN ({','.join('?' * len(query.addresses))})")
            params.extend(query.addresses)
        for position, options in enumerate(query.topics[:4]):
            if options:
                column = f"{prefix if position == 0 else ''}topic{position}"
                clauses.append(f"{column} IN ({','.join('?' * len(options))})")
                params.extend(options)
        sql = f"SELECT * FROM logs WHERE {' AND '.join(clauses)} ORDER BY block_number, log_index"
        if limit is not None:
            sql += f" LIMIT {limit}"
        return [_entry(row) for row in self._read_within_budget(sql, params)]

    def _read_within_budget(self, sql: str, params: list[Any]) -> list[Any]:
        """The rows of one log query, stopped after ``LOG_QUERY_BUDGET_S`` (``IndexLimitError``):
        queries take turns on the reader, so one without an end would hold every other."""
        deadline = time.monotonic() + LOG_QUERY_BUDGET_S
        with self._reader_lock:
            self._reader.set_progress_handler(
                lambda: time.monotonic() > deadline, QUERY_PROGRESS_STEPS
            )
            try:
                return self._reader.execute(sql, params).fetchall()
            except sqlite3.OperationalError as exc:
                if "interrupted" not in str(exc):
                    raise
                raise IndexLimitError(
                    f"query timeout exceeded ({LOG_QUERY_BUDGET_S:g} s); narrow the block "
                    "range or the filter"
                ) from exc
            finally:
                self._reader.set_progress_handler(None, 0)

    def robot(self, address: str) -> dict[str, Any] | None:
        with self._lock:
            row = self._db.execute("SELECT * FROM robots WHERE address = ?", (address,)).fetchone()
            roles = self._db.execute(
                "SELECT role FROM roles WHERE address = ? ORDER BY role", (address,)
            ).fetchall()
        if row is None:
            return None
        _, metadata, registered_at, block, active, suspended = row
        return {
            "address": address,
            "metadata_cid": bytes(metadata),
            "registered_at": registered_at,
            "registered_block": block,
            "active": bool(active),
            "suspended": bool(suspended),
            "roles": [bytes(role[0]) for role in roles],
        }

    def pending(self, address: str | None = None, limit: int = 100) -> list[dict[str, Any]]:
        """Registrations awaiting a registrar (Approved mode), oldest first."""
        where, params = ("WHERE address = ?", [address]) if address else ("", [])
        sql = f"SELECT * FROM registrations {where} ORDER BY requested_block, address LIMIT ?"
        with self._lock:
            rows = self._db.execute(sql, [*params, limit]).fetchall()
        return [
            {
                "address": who,
                "metadata_cid": bytes(metadata),
                "requested_at": requested_at,
                "requested_block": block,
            }
            for who, metadata, requested_at, block in rows
        ]

    def advertisements(
        self,
        cid: bytes | None,
        advertiser: str | None,
        since: int,
        limit: int,
        after_log_index: int | None = None,
    ) -> list[dict[str, Any]]:
        """Advertised events from block ``since`` on, oldest first; with ``after_log_index``,
        those of block ``since`` only past that log index: the position a reader saved, so
        that it reads on past a block holding more events than ``limit``. Both may be any
        uint64: past SQLite's integers they are clamped, to the same answer."""
        since = min(since, MAX_SQLITE_INTEGER)
        if after_log_index is None:
            clauses, params = ["block_number >= ?"], [since]
        else:
            clauses = ["(block_number, log_index) > (?, ?)"]
            params = [since, min(after_log_index, MAX_SQLITE_INTEGER)]
        if cid is not None:
            clauses.append("cid = ?")
            params.append(cid)  # type: ignore[arg-type]
        if advertiser is not None:
            clauses.append("advertiser = ?")
            params.append(advertiser)  # type: ignore[arg-type]
        sql = (
            f"SELECT * FROM advertisements WHERE {' AND '.join(clauses)} "
            "ORDER BY block_number, log_index LIMIT ?"
        )
        with self._lock:
            rows = self._db.execute(sql, [*params, limit]).fetchall()
        return [
            {
                "cid": bytes(cid_),
                "advertiser": who,
                "description_cid": bytes(description),
                "first": bool(first),
                "timestamp": timestamp,
                "block_number": block,
                "log_index": log_index,
                "tx_hash": bytes(tx),
            }
            for block, log_index, cid_, who, description, first, timestamp, tx in rows
        ]

    def anchors(self, node: str | None, epoch: int | None, limit: int) -> list[dict[str, Any]]:
        """Anchored roots by node and/or epoch (any uint64), in chain order."""
        clauses: list[str] = []
        params: list[Any] = []
        if node is not None:
            clauses.append("node = ?")
            params.append(node)
        if epoch is not None:
            clauses.append("epoch = ?")
            params.append(biased(epoch))
        where = f"WHERE {' AND '.join(clauses)}" if clauses else ""
        sql = f"SELECT * FROM anchors {where} ORDER BY block_number, node LIMIT ?"
        with self._lock:
            rows = self._db.execute(sql, [*params, limit]).fetchall()
        return [
            {
                "node": node_,
                "epoch": unbiased(epoch_),
                "root": bytes(root),
                "record_count": unbiased(count),
                "timestamp": timestamp,
                "block_number": block,
                "tx_hash": bytes(tx),
            }
            for node_, epoch_, root, count, timestamp, block, tx in rows
        ]


def _entry(row: Sequence[Any]) -> LogEntry:
    block, log_index, block_hash, tx_hash, tx_index, address, t0, t1, t2, t3, data = row
    return LogEntry(
        block_number=block,
        block_hash=bytes(block_hash),
        tx_hash=bytes(tx_hash),
        tx_index=tx_index,
        log_index=log_index,
        address=bytes(address),
        topics=tuple(bytes(t) for t in (t0, t1, t2, t3) if t is not None),
        data=bytes(data),
    )


def _time(log: DecodedLog) -> int:
    """The event's uint64 ``timestamp`` as stored, refused past SQLite's integers naming
    the event and the time (``_apply`` then leaves the event out). Only a node's lie or a
    clock set past the year 292 billion names one; OverflowError did not say which value."""
    timestamp = int(log.args["timestamp"])
    if timestamp > MAX_SQLITE_INTEGER:
        raise ValueError(
            f"{log.event} timestamp {timestamp} is past 2^63 - 1, the largest integer the "
            "index holds"
        )
    return timestamp


def _registered(db: sqlite3.Connection, log: DecodedLog, entry: LogEntry) -> None:
    db.execute(
        "INSERT OR REPLACE INTO robots VALUES (?, ?, ?, ?, 1, 0)",
        (log.args["robot"], log.args["metadataCid"], _time(log), entry.block_number),
    )


def _requested(db: sqlite3.Connection, log: DecodedLog, entry: LogEntry) -> None:
    db.execute(
        "INSERT OR REPLACE INTO registrations VALUES (?, ?, ?, ?)",
        (log.args["robot"], log.args["metadataCid"], _time(log), entry.block_number),
    )


def _decided(db: sqlite3.Connection, log: DecodedLog, _: LogEntry) -> None:
    """Approved or rejected: no longer pending (an approval also emits RobotRegistered)."""
    db.execute("DELETE FROM registrations WHERE address = ?", (log.args["robot"],))


def _metadata(db: sqlite3.Connection, log: DecodedLog, _: LogEntry) -> None:
    db.execute(
        "UPDATE robots SET metadata_cid = ? WHERE address = ?",
        (log.args["metadataCid"], log.args["robot"]),
    )


def _activation(db: sqlite3.Connection, log: DecodedLog, _: LogEntry) -> None:
    db.execute(
        "UPDATE robots SET active = ? WHERE address = ?", (log.args["active"], log.args["robot"])
    )


def _suspension(db: sqlite3.Connection, log: DecodedLog, _: LogEntry) -> None:
    db.execute(
        "UPDATE robots SET suspended = ? WHERE address = ?",
        (log.args["suspended"], log.args["robot"]),
    )


def _granted(db: sqlite3.Connection, log: DecodedLog, _: LogEntry) -> None:
    db.execute("INSERT OR IGNORE INTO roles VALUES (?, ?)", (log.args["account"], log.args["role"]))


def _revoked(db: sqlite3.Connection, log: DecodedLog, _: LogEntry) -> None:
    db.execute(
        "DELETE FROM roles WHERE address = ? AND role = ?", (log.args["account"], log.args["role"])
    )


def _advertised(db: sqlite3.Connection, log: DecodedLog, entry: LogEntry) -> None:
    args = log.args
    db.execute(
        "INSERT OR IGNORE INTO advertisements VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
        (
            entry.block_number,
            entry.log_index,
            args["cid"],
            args["advertiser"],
            args["descriptionCid"],
            args["first"],
            _time(log),
            entry.tx_hash,
        ),
    )


def _anchored(db: sqlite3.Connection, log: DecodedLog, entry: LogEntry) -> None:
    args = log.args
    db.execute(
        "INSERT OR REPLACE INTO anchors VALUES (?, ?, ?, ?, ?, ?, ?)",
        (
            args["node"],
            biased(args["epoch"]),
            args["root"],
            biased(args["recordCount"]),
            _time(log),
            entry.block_number,
            entry.tx_hash,
        ),
    )


_HANDLERS = {
    "RobotRegistered": _registered,
    "RegistrationRequested": _requested,
    "RegistrationApproved": _decided,
    "RegistrationRejected": _decided,
    "MetadataUpdated": _metadata,
    "RobotActivationChanged": _activation,
    "RobotSuspensionChanged": _suspension,
    "RoleGranted": _granted,
    "RoleRevoked": _revoked,
    "Advertised": _advertised,
    "Anchored": _anchored,
}
