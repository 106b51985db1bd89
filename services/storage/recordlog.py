"""The record logs: one append-only RFC 6962 log per template version, the storage node's truth.

Every view of the records (segments, time and numeric indexes, keywords) is derived from these
logs and rebuilt past its last durable mark at start, so the logs alone decide what was
acknowledged. A write is acknowledged when :meth:`RecordLogs.append_batch` returns: by then
its records and their leaf hashes are on disk (one group commit per call, never one per
record), in every log it names or in none.

Each template version ``name@version`` has a directory under the root with three files:

``records.log``
    the frames, back to back: ``>II`` (record length, meta length), the record, the meta.
``index.bin``
    40 bytes per entry: ``>Q`` offset of its frame in ``records.log`` and its leaf hash. The
    index is the commit point: it is written and fsynced after ``records.log``, so an entry
    in the index always has its frame on disk, and a frame past the index is a torn tail.
``subtrees.bin``
    the hash of every complete, aligned subtree of :data:`CHUNK` leaves, in order: derived
    from the index, fsynced with it when it grows, checked and completed at open.

Beside the directories, ``batch.journal`` names the last batch (each log's first index and
count) before any of its index entries is written. A batch over two logs whose first index
reached the disk and whose second did not is undone at open: a request is stored whole or
not at all, and a client that retries after the crash does not store the first part twice.

Proofs need ``subtree(start, end)`` hashes. Subtrees of at least :data:`CHUNK` leaves are
folded from the chunk hashes, kept in memory level by level (``n / CHUNK`` hashes, 4 KiB per
million records per level); smaller ones are hashed from at most ``CHUNK`` leaf hashes read in
one ``pread``. A proof in a log of a million records reads a few kilobytes and computes a few
hundred hashes.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import re
import struct
import threading
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from robocloud import merkle
from services.common.durable import fsync_dir, write_all

CHUNK_BITS = 8
CHUNK = 1 << CHUNK_BITS
"""Leaves per cached subtree: the unit below which hashes are computed from leaf hashes."""

FRAME_HEADER = struct.Struct(">II")
INDEX_ENTRY = struct.Struct(">Q32s")
READ_BATCH = 4096
"""Entries read per ``pread`` when iterating a log."""

TEMPLATE_ID = re.compile(r"[a-z][a-z0-9_]{0,62}@[1-9][0-9]{0,8}")

BATCH_JOURNAL = "batch.journal"
"""Under the root: the last batch appended, named before its index entries are written."""

JOURNAL_HEADER = struct.Struct(">I32s")
"""The journal's head: its JSON's length and SHA-256."""
JOURNAL_PAGE = 4096

log_event = logging.getLogger("robocloud.storage.records")


class RecordLogError(Exception):
    """Base of the record logs' own errors."""


class InvalidTemplateId(RecordLogError, ValueError):
    def __init__(self, template_id: str) -> None:
        super().__init__(f"{template_id!r} is not a template id (name@version)")
        self.template_id = template_id


class EntryNotFound(RecordLogError, LookupError):
    def __init__(self, template_id: str, index: int, size: int) -> None:
        super().__init__(f"{template_id} has no entry {index} (it holds {size})")
        self.template_id = template_id
        self.index = index
        self.size = size


class InvalidTreeSize(RecordLogError, ValueError):
    """A tree size or index range that the log cannot answer for (beyond its head, reversed)."""

    def __init__(self, template_id: str, message: str) -> None:
        super().__init__(f"{template_id}: {message}")
        self.template_id = template_id


class LogCorrupt(RecordLogError):
    """What the disk holds contradicts the log's own hashes: never answered as if valid."""


@dataclass(frozen=True)
class LogEntry:
    record: bytes
    """The canonical (JCS) record: the Merkle leaf's data."""
    meta: bytes
    """JSON, not hashed: signer address, signed request digest, signature, received time."""


def _pread_exact(fd: int, size: int, offset: int) -> bytes:
    parts: list[bytes] = []
    while size:
        part = os.pread(fd, size, offset)
        if not part:
            raise LogCorrupt(f"a read of {size} bytes at {offset} ends early")
        parts.append(part)
        size -= len(part)
        offset += len(part)
    return b"".join(parts)


@dataclass(frozen=True)
class _Staged:
    """A batch's entries for one log, their frames on disk, their index entries not yet."""

    log: _TemplateLog
    first: int
    count: int
    index: bytes
    records_end: int
    chunks: tuple[bytes, ...]
    """Hashes of the chunks the batch completes."""


class _TemplateLog:
    """One template version's log; every method is called with ``lock`` held."""

    def __init__(self, template_id: str, directory: Path) -> None:
        self.template_id = template_id
        self.lock = threading.Lock()
        directory.mkdir(exist_ok=True)
        self._records = os.open(directory / "records.log", os.O_RDWR | os.O_CREAT, 0o600)
        self._index = os.open(directory / "index.bin", os.O_RDWR | os.O_CREAT, 0o600)
        self._subtrees = os.open(directory / "subtrees.bin", os.O_RDWR | os.O_CREAT, 0o600)
        self.size = 0
        self.indexed = 0
        """Whole index entries found at open, before a torn tail was dropped."""
        self._records_end = 0
        self._levels: list[list[bytes]] = [[]]
        """``_levels[k][i]``: the hash of leaves ``[i * CHUNK * 2**k, (i + 1) * CHUNK * 2**k)``."""
        self._chunks_saved = 0
        """How many of ``_levels[0]`` ``subtrees.bin`` holds."""
        self._recover()

    def close(self) -> None:
        for fd in (self._records, self._index, self._subtrees):
            os.close(fd)

    def _recover(self) -> None:
        """Drop a torn tail left by a crash: nothing past the last complete index entry counts."""
        index_bytes = os.fstat(self._index).st_size
        records_bytes = os.fstat(self._records).st_size
        size = index_bytes // INDEX_ENTRY.size
        self.indexed = size
        while size:
            offset, leaf = self._index_entry(size - 1)
            end = self._frame_end(offset, records_bytes)
            if end is not None and merkle.leaf_hash(self._read_record(offset)) == leaf:
                break
            size -= 1
        self.size = size
        self._records_end = 0 if size == 0 else self._frame_end_of(size - 1)
        os.ftruncate(self._index, size * INDEX_ENTRY.size)
        os.ftruncate(self._records, self._records_end)
        self._recover_subtrees()

    def _frame_end(self, offset: int, records_bytes: int) -> int | None:
        if offset + FRAME_HEADER.size > records_bytes:
            return None
        record_len, meta_len = FRAME_HEADER.unpack(
            _pread_exact(self._records, FRAME_HEADER.size, offset)
        )
        end = offset + FRAME_HEADER.size + record_len + meta_len
        return end if end <= records_bytes else None

    def _frame_end_of(self, index: int) -> int:
        offset, _ = self._index_entry(index)
        end = self._frame_end(offset, os.fstat(self._records).st_size)
        if end is None:
            raise LogCorrupt(f"{self.template_id}: the frame of entry {index} is cut short")
        return end

    def _read_record(self, offset: int) -> bytes:
        record_len, _ = FRAME_HEADER.unpack(_pread_exact(self._records, FRAME_HEADER.size, offset))
        return _pread_exact(self._records, record_len, offset + FRAME_HEADER.size)

    def _recover_subtrees(self) -> None:
        """Keep the chunk hashes that the index backs, recompute the rest, check the last kept."""
        complete = self.size // CHUNK
        stored = min(os.fstat(self._subtrees).st_size // merkle.HASH_SIZE, complete)
        data = _pread_exact(self._subtrees, stored * merkle.HASH_SIZE, 0)
        chunks = [data[i : i + merkle.HASH_SIZE] for i in range(0, len(data), merkle.HASH_SIZE)]
        if chunks and chunks[-1] != self._chunk_from_leaves(len(chunks) - 1):
            chunks = []
        os.ftruncate(self._subtrees, len(chunks) * merkle.HASH_SIZE)
        missing = [self._chunk_from_leaves(i) for i in range(len(chunks), complete)]
        if missing:
            os.pwrite(self._subtrees, b"".join(missing), len(chunks) * merkle.HASH_SIZE)
            os.fdatasync(self._subtrees)
        self._levels = [[]]
        for chunk in chunks + missing:
            self._add_chunk(chunk)
        self._chunks_saved = len(self._levels[0])

    def _chunk_from_leaves(self, chunk: int) -> bytes:
        return merkle.root(self.leaf_hashes(chunk * CHUNK, (chunk + 1) * CHUNK))

    def _add_chunk(self, value: bytes) -> None:
        level = 0
        self._levels[0].append(value)
        while len(self._levels[level]) % 2 == 0:
            pair = self._levels[level][-2:]
            level += 1
            if len(self._levels) == level:
                self._levels.append([])
            self._levels[level].append(merkle.node_hash(pair[0], pair[1]))

    def _index_entry(self, index: int) -> tuple[int, bytes]:
        offset, leaf = INDEX_ENTRY.unpack(
            _pread_exact(self._index, INDEX_ENTRY.size, index * INDEX_ENTRY.size)
        )
        return offset, leaf

    def _index_range(self, start: int, stop: int) -> list[tuple[int, bytes]]:
        data = _pread_exact(
            self._index, (stop - start) * INDEX_ENTRY.size, start * INDEX_ENTRY.size
        )
        return list(INDEX_ENTRY.iter_unpack(data))

    def leaf_hashes(self, start: int, stop: int) -> list[bytes]:
        return [leaf for _, leaf in self._index_range(start, stop)]

    def write_frames(self, entries: Sequence[LogEntry]) -> _Staged:
        """Write and sync ``entries``' frames past the end; nothing counts until the index."""
        first = self.size
        frames: list[bytes] = []
        index: list[bytes] = []
        leaves: list[bytes] = []
        offset = self._records_end
        for entry in entries:
            frames.append(FRAME_HEADER.pack(len(entry.record), len(entry.meta)))
            frames.append(entry.record)
            frames.append(entry.meta)
            leaves.append(merkle.leaf_hash(entry.record))
            index.append(INDEX_ENTRY.pack(offset, leaves[-1]))
            offset += FRAME_HEADER.size + len(entry.record) + len(entry.meta)
        staged = _Staged(
            self, first, len(entries), b"".join(index), offset, self._chunks_completed(leaves)
        )
        os.lseek(self._records, self._records_end, os.SEEK_SET)
        write_all(self._records, b"".join(frames))
        os.fdatasync(self._records)
        return staged

    def write_index(self, staged: _Staged) -> None:
        """Commit ``staged``'s entries on disk; readers see them only after :meth:`publish`."""
        os.lseek(self._index, staged.first * INDEX_ENTRY.size, os.SEEK_SET)
        write_all(self._index, staged.index)
        os.fdatasync(self._index)

    def discard(self, staged: _Staged) -> None:
        """Undo a batch that failed before it was shown: back to ``staged.first``.

        Best effort, as it runs while another error is raised: what it cannot truncate, the
        next batch writes over from ``staged.first``, and the journal still names this one.
        """
        try:
            os.ftruncate(self._index, staged.first * INDEX_ENTRY.size)
            os.ftruncate(self._records, self._records_end)
            os.fdatasync(self._index)
        except OSError as exc:
            log_event.warning(
                "a failed batch not truncated",
                extra={"template": self.template_id, "error": str(exc)},
            )

    def _chunks_completed(self, leaves: list[bytes]) -> tuple[bytes, ...]:
        """The hashes of the chunks that ``leaves``, appended, complete: worked out before the
        batch commits, so that nothing that reads the disk runs between commit and publish."""
        start = len(self._levels[0]) * CHUNK
        pending = self.leaf_hashes(start, self.size) + leaves
        return tuple(
            merkle.root(pending[at : at + CHUNK])
            for at in range(0, len(pending) - CHUNK + 1, CHUNK)
        )

    def publish(self, staged: _Staged) -> None:
        """Show a committed batch to readers; no I/O, so it cannot fail halfway through a
        batch and leave one log's part shown and another's hidden."""
        self._records_end = staged.records_end
        self.size = staged.first + staged.count
        for chunk in staged.chunks:
            self._add_chunk(chunk)

    def save_chunks(self) -> None:
        """Bring ``subtrees.bin`` up to the chunk hashes in memory.

        A failure is logged, not raised: the batch is committed and shown by then, and the
        file is only a cache that the next save, or the next open, completes.
        """
        saved = self._chunks_saved
        unsaved = self._levels[0][saved:]
        if not unsaved:
            return
        try:
            os.pwrite(self._subtrees, b"".join(unsaved), saved * merkle.HASH_SIZE)
            os.fdatasync(self._subtrees)
        except OSError as exc:
            log_event.warning(
                "chunk hashes not saved; the next append or open saves them",
                extra={"template": self.template_id, "error": str(exc)},
            )
            with contextlib.suppress(OSError):
                os.ftruncate(self._subtrees, saved * merkle.HASH_SIZE)
            return
        self._chunks_saved = len(self._levels[0])

    def truncate(self, size: int) -> None:
        """Drop every entry from ``size`` on, durably: the undo of a batch torn by a crash."""
        os.ftruncate(self._index, size * INDEX_ENTRY.size)
        os.fdatasync(self._index)
        self._recover()

    def entry(self, index: int) -> LogEntry:
        if not 0 <= index < self.size:
            raise EntryNotFound(self.template_id, index, self.size)
        offset, leaf = self._index_entry(index)
        return self._check(index, leaf, self._read_frame(offset))

    def _read_frame(self, offset: int) -> bytes:
        record_len, meta_len = FRAME_HEADER.unpack(
            _pread_exact(self._records, FRAME_HEADER.size, offset)
        )
        return _pread_exact(self._records, FRAME_HEADER.size + record_len + meta_len, offset)

    def _check(self, index: int, leaf: bytes, frame: bytes) -> LogEntry:
        record_len, _ = FRAME_HEADER.unpack_from(frame)
        record = frame[FRAME_HEADER.size : FRAME_HEADER.size + record_len]
        if merkle.leaf_hash(record) != leaf:
            raise LogCorrupt(f"{self.template_id}: entry {index} does not match its leaf hash")
        return LogEntry(record=record, meta=frame[FRAME_HEADER.size + record_len :])

    def entries_batch(self, start: int, stop: int) -> list[LogEntry]:
        """Entries ``[start, stop)`` from one read of the index and one of the records."""
        rows = self._index_range(start, stop)
        if not rows:
            return []
        base = rows[0][0]
        end = self._records_end if stop == self.size else self._index_entry(stop)[0]
        data = _pread_exact(self._records, end - base, base)
        bounds = [offset - base for offset, _ in rows] + [end - base]
        return [
            self._check(start + i, leaf, data[bounds[i] : bounds[i + 1]])
            for i, (_, leaf) in enumerate(rows)
        ]

    def subtree(self, start: int, end: int) -> bytes:
        """MTH of leaves ``[start, end)``: cached chunks where aligned, leaf hashes below."""
        width = end - start
        if width & (width - 1) == 0 and start % width == 0 and width >= CHUNK:
            level = width.bit_length() - 1 - CHUNK_BITS
            return self._levels[level][start >> (CHUNK_BITS + level)]
        if width <= CHUNK:
            return merkle.root(self.leaf_hashes(start, end))
        split = 1 << ((width - 1).bit_length() - 1)
        return merkle.node_hash(
            self.subtree(start, start + split), self.subtree(start + split, end)
        )


def _write_journal(fd: int, staged: Sequence[_Staged]) -> None:
    """Name a batch before any of its index entries is written: its logs and their ranges,
    behind their length and SHA-256, so that a journal torn by a crash reads as no batch.

    Padded to whole pages and written in place: the file keeps its size from batch to
    batch, so the sync writes one page of data and no metadata.
    """
    payload = json.dumps(
        {part.log.template_id: [part.first, part.count] for part in staged},
        separators=(",", ":"),
    ).encode()
    data = JOURNAL_HEADER.pack(len(payload), hashlib.sha256(payload).digest()) + payload
    os.pwrite(fd, data.ljust(-(-len(data) // JOURNAL_PAGE) * JOURNAL_PAGE, b"\0"), 0)
    os.fdatasync(fd)


def _read_journal(fd: int) -> dict[str, tuple[int, int]] | None:
    """The last batch the journal names, or None when it is empty or torn: a torn journal
    means the crash came before the batch wrote any index entry."""
    data = _pread_exact(fd, os.fstat(fd).st_size, 0)
    if len(data) < JOURNAL_HEADER.size:
        return None
    length, digest = JOURNAL_HEADER.unpack_from(data)
    payload = data[JOURNAL_HEADER.size : JOURNAL_HEADER.size + length]
    if len(payload) != length or hashlib.sha256(payload).digest() != digest:
        return None
    named = json.loads(payload)
    return {
        template_id: (int(first), int(count))
        for template_id, (first, count) in named.items()
        if TEMPLATE_ID.fullmatch(template_id)
    }


class RecordLogs:
    """The logs of every template version under ``root``; safe to share between threads.

    Appends are serialised (one batch journal); reads of a log wait only for an append to
    that log.
    """

    def __init__(self, root: Path) -> None:
        self.directory = root
        root.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._append_lock = threading.Lock()
        self._logs: dict[str, _TemplateLog] = {}
        for directory in sorted(root.iterdir()):
            if directory.is_dir() and TEMPLATE_ID.fullmatch(directory.name):
                self._logs[directory.name] = _TemplateLog(directory.name, directory)
        journal = root / BATCH_JOURNAL
        created = not journal.exists()
        self._journal = os.open(journal, os.O_RDWR | os.O_CREAT, 0o600)
        if created:
            fsync_dir(root)
        self._undo_torn_batch()

    def close(self) -> None:
        with self._lock:
            for log in self._logs.values():
                with log.lock:
                    log.close()
            self._logs.clear()
            if self._journal >= 0:
                os.close(self._journal)
                self._journal = -1

    def _undo_torn_batch(self) -> None:
        """Truncate every log of the journal's batch to where the batch began, unless each
        log's index holds all of its entries: a crash between two index writes left a part.

        Index entries, not the size after recovery, decide: a frame damaged after it was
        indexed (the disk, not a crash) costs its own entry at open, not its whole batch.
        """
        batch = _read_journal(self._journal)
        if batch is None:
            return
        indexed = {
            template_id: log.indexed if (log := self._logs.get(template_id)) else 0
            for template_id in batch
        }
        if all(
            indexed[template_id] >= first + count for template_id, (first, count) in batch.items()
        ):
            return
        for template_id, (first, _) in batch.items():
            log = self._logs.get(template_id)
            if log is not None and log.size > first:
                log.truncate(first)
        log_event.warning(
            "a batch torn by a crash was undone",
            extra={"logs": {template_id: first for template_id, (first, _) in batch.items()}},
        )

    def _log(self, template_id: str, *, create: bool = False) -> _TemplateLog | None:
        if not TEMPLATE_ID.fullmatch(template_id):
            raise InvalidTemplateId(template_id)
        with self._lock:
            log = self._logs.get(template_id)
            if log is None and create:
                log = _TemplateLog(template_id, self.directory / template_id)
                fsync_dir(self.directory)
                self._logs[template_id] = log
            return log

    def append(self, template_id: str, entries: Sequence[LogEntry]) -> int:
        """Append ``entries`` in order; the index of the first. Durable when this returns."""
        return self.append_batch({template_id: entries})[template_id]

    def append_batch(self, batch: Mapping[str, Sequence[LogEntry]]) -> dict[str, int]:
        """Append to several logs as one write: each log's first new index.

        Durable when this returns, and all or nothing across the logs, through a crash too:
        every frame is synced, then the journal names the batch, then the indexes are
        written; a start that finds the journal's batch in part undoes it
        (:meth:`_undo_torn_batch`). Readers see the new entries only once every log holds
        them, so nothing (a root anchored on chain, a keyword mark) can refer to a part.
        """
        logs = {template_id: self._log(template_id, create=True) for template_id in sorted(batch)}
        with self._append_lock, contextlib.ExitStack() as held:
            for log in logs.values():
                assert log is not None
                held.enter_context(log.lock)
            staged: list[_Staged] = []
            try:
                for template_id, log in logs.items():
                    assert log is not None
                    if batch[template_id]:
                        staged.append(log.write_frames(batch[template_id]))
                if staged:
                    _write_journal(self._journal, staged)
                for part in staged:
                    part.log.write_index(part)
            except BaseException:
                for part in staged:
                    part.log.discard(part)
                raise
            for part in staged:
                part.log.publish(part)
            for part in staged:
                part.log.save_chunks()
            firsts = {part.log.template_id: part.first for part in staged}
            return {
                template_id: firsts.get(template_id, log.size if log is not None else 0)
                for template_id, log in logs.items()
            }

    def size(self, template_id: str) -> int:
        log = self._log(template_id)
        if log is None:
            return 0
        with log.lock:
            return log.size

    def sizes(self) -> dict[str, int]:
        """Every log's size, read together: the heads an epoch is built from."""
        with self._lock:
            logs = list(self._logs.items())
        heads: dict[str, int] = {}
        for template_id, log in sorted(logs):
            with log.lock:
                heads[template_id] = log.size
        return heads

    def template_ids(self) -> list[str]:
        with self._lock:
            return sorted(self._logs)

    def entry(self, template_id: str, index: int) -> LogEntry:
        log = self._log(template_id)
        if log is None:
            raise EntryNotFound(template_id, index, 0)
        with log.lock:
            return log.entry(index)

    def entries(self, template_id: str, start: int, stop: int) -> Iterator[LogEntry]:
        """Entries ``[start, stop)`` (``stop`` clamped to the size), read in batches."""
        log = self._log(template_id)
        if log is None:
            return
        if start < 0 or stop < start:
            raise InvalidTreeSize(template_id, f"no entries from {start} to {stop}")
        position = start
        while True:
            with log.lock:
                end = min(stop, log.size, position + READ_BATCH)
                if position >= end:
                    return
                batch = log.entries_batch(position, end)
            yield from batch
            position = end

    def _sized_log(self, template_id: str, size: int) -> _TemplateLog | None:
        log = self._log(template_id)
        current = 0 if log is None else log.size
        if not 0 <= size <= current:
            raise InvalidTreeSize(
                template_id, f"no tree of {size} leaves (the log holds {current})"
            )
        return log

    def root(self, template_id: str, size: int) -> bytes:
        """The root of the first ``size`` entries (RFC 6962 MTH; SHA-256 of nothing for 0)."""
        log = self._sized_log(template_id, size)
        if log is None or size == 0:
            return merkle.EMPTY_ROOT
        with log.lock:
            return log.subtree(0, size)

    def inclusion_proof(self, template_id: str, index: int, size: int) -> list[bytes]:
        log = self._sized_log(template_id, size)
        if log is None or not 0 <= index < size:
            raise EntryNotFound(template_id, index, size)
        with log.lock:
            return merkle.inclusion_proof(index, size, log.subtree)

    def consistency_proof(self, template_id: str, first: int, second: int) -> list[bytes]:
        log = self._sized_log(template_id, second)
        if not 0 <= first <= second:
            raise InvalidTreeSize(template_id, f"no consistency proof from {first} to {second}")
        if log is None:
            return []
        with log.lock:
            return merkle.consistency_proof(first, second, log.subtree)
