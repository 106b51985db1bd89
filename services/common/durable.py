"""Durable file writes: what a crash may interrupt, it must not leave half-written.

Every write goes to a temporary file in the same directory, is fsynced, renamed over the
target (atomic on POSIX) and the directory is fsynced so the rename itself survives a crash.
State that changes record by record goes to SQLite instead, opened by ``open_sqlite`` and
written in ``write_transaction``s; a write whose COMMIT failed is made unrecoverable by
``void_failed_commit``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

log = logging.getLogger("robocloud.durable")


def open_sqlite(
    path: Path, schema: str, *, synchronous: Literal["FULL", "NORMAL"]
) -> sqlite3.Connection:
    """A WAL-mode connection in autocommit mode, shared across threads, with ``schema`` applied.

    Callers serialise access with their own lock and open transactions explicitly.
    ``synchronous=FULL`` fsyncs every commit (what is acknowledged survives a power cut);
    ``NORMAL`` only keeps the database consistent, for state that can be rebuilt.
    """
    connection = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    connection.execute("PRAGMA journal_mode=WAL")
    connection.execute(f"PRAGMA synchronous={synchronous}")
    connection.executescript(schema)
    return connection


FAILED_COMMIT_SCHEMA = """
CREATE TABLE IF NOT EXISTS failed_commit (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    at REAL NOT NULL
)
"""
"""``failed_commit`` holds the time of the last COMMIT that failed; writing it is what voids
that COMMIT's frames (``void_failed_commit``)."""


def void_failed_commit(connection: sqlite3.Connection) -> None:
    """Make sure no recovery finds what a failed COMMIT on ``connection`` wrote to its
    write-ahead log; call it at once after the COMMIT (or autocommit statement) raised.

    A commit that fails (the disk refuses the fsync of the ``-wal`` file) is rolled back in
    this process, but its frames, commit marker included, may already be in the log's file
    past the last frame SQLite counts, and a restart's WAL recovery reads them: it brought
    back a write the process had answered as failed. So this writes a one-row commit to the
    ``failed_commit`` table (created if missing) right away. SQLite writes the next commit
    from the first frame the failed one used (or into a log restarted with new salts), and
    WAL recovery stops at the first frame whose checksum chain breaks: one frame written
    there voids every frame after it. If this commit's fsync fails as well, its frames are in
    the file all the same (only their sync failed), and what they hold changes nothing the
    caller reads; only a failure to write them at all is logged.
    """
    try:
        if connection.in_transaction:
            connection.execute("ROLLBACK")
        connection.execute(FAILED_COMMIT_SCHEMA)
        connection.execute("INSERT OR REPLACE INTO failed_commit VALUES (1, ?)", (time.time(),))
    except sqlite3.Error as exc:
        if exc.sqlite_errorname != "SQLITE_IOERR_FSYNC":
            log.error(
                "a failed commit could not be voided: a restart before the next commit may find it",
                extra={"error": exc.sqlite_errorname},
            )


@contextlib.contextmanager
def write_transaction(connection: sqlite3.Connection) -> Iterator[None]:
    """One write transaction on ``connection``: committed whole or rolled back, and a COMMIT
    that failed leaves nothing a restart could find (``void_failed_commit``).

    An I/O error or a full disk inside may have rolled the transaction back already (SQLite
    does so itself); a ROLLBACK then is refused ("no transaction is active"), and that refusal
    was raised in place of the error that failed the write.
    """
    connection.execute("BEGIN IMMEDIATE")
    try:
        yield
    except BaseException:
        if connection.in_transaction:
            connection.execute("ROLLBACK")
        raise
    try:
        connection.execute("COMMIT")
    except sqlite3.Error:
        void_failed_commit(connection)
        raise


def fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_all(fd: int, data: bytes) -> None:
    """Write all of ``data``: ``os.write`` may write less (a disk filling, a file size limit)
    and say so only in its count; what it cannot write at all raises."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def write_synced(path: Path, data: bytes, *, mode: int = 0o644) -> None:
    """Write ``path`` and fsync it, in place: for a file that nothing reads until a later
    atomic write (a manifest, say) names it, and that is removed if a crash comes first."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        write_all(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: Path, data: bytes, *, mode: int = 0o644) -> None:
    """Replace ``path`` with ``data`` so that readers see the old or the new file, never a mix."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write_synced(tmp, data, mode=mode)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)
    fsync_dir(path.parent)


MIN_DEAD_LINES = 1_000
"""Dead lines (removed or replaced entries) a journal holds before an open compacts it:
fewer cost little to read again."""


class AppendLog:
    """An append-only file of lines, fsynced per append: a journal that survives kill -9.

    Every line in the file was acknowledged whole. A torn last line (a crash, or a disk that
    filled, in the middle of a write) was not: it is cut off at open, and an append that fails
    is cut off before its error is raised, since a line glued onto a torn one was read as one
    garbled line (a store that could not start, a nonce forgotten and so replayable).
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
        self._size = self._cut_torn_line()

    def _cut_torn_line(self) -> int:
        data = self.path.read_bytes()
        whole = data.rfind(b"\n") + 1
        if whole != len(data):
            os.ftruncate(self._fd, whole)
            os.fsync(self._fd)
        return whole

    def append(self, line: str) -> None:
        """Write ``line`` and sync it; on failure the file is as it was before, and it raises."""
        if "\n" in line:
            raise ValueError("a journal line cannot contain a newline")
        data = (line + "\n").encode()
        try:
            write_all(self._fd, data)
            os.fsync(self._fd)
        except BaseException:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, self._size)
            raise
        self._size += len(data)

    def read_lines(self) -> list[str]:
        return self.path.read_bytes().decode().splitlines()

    def rewrite(self, lines: list[str]) -> None:
        """Compact the log to ``lines`` atomically.

        The file is opened again whether or not this raises: a failure after the rename
        (syncing the directory) left the descriptor on the replaced file, and every later
        line went to a file no name leads to.
        """
        try:
            atomic_write(self.path, "".join(f"{line}\n" for line in lines).encode(), mode=0o600)
        finally:
            os.close(self._fd)
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)
            self._size = os.fstat(self._fd).st_size

    def compact_at_open(self, live: list[str], read: int, *, force: bool = False) -> None:
        """Replace the journal, which held ``read`` lines at open, with the ``live`` ones, when
        enough of it is dead to be worth a rewrite: :data:`MIN_DEAD_LINES`, and no fewer than
        the live lines; with ``force`` (lines of an older format to write anew) in any case.
        A rewrite the disk refuses is logged and the journal kept as it is: rewritten at
        every open, a full disk stopped the service from starting again, even to free space."""
        dead = read - len(live)
        if not force and dead < max(MIN_DEAD_LINES, len(live)):
            return
        try:
            self.rewrite(live)
        except OSError as exc:
            log.warning(
                "journal not compacted; appending to it as it is",
                extra={"path": str(self.path), "error": str(exc)},
            )

    def close(self) -> None:
        os.close(self._fd)


def generated_secret(path: Path) -> str:
    """The secret kept in ``path`` (0600), generated and made durable the first time.

    Written whole and synced under a temporary name, then linked into place: a crash leaves
    the file whole or absent, and of two processes starting together the second's link fails
    and it reads the first's secret. An empty file, which a crash between creating and
    writing it used to leave (and the node then never started), counts as absent.
    """
    while True:
        try:
            existing: str | None = path.read_text().strip()
        except FileNotFoundError:
            existing = None
        if existing:
            return existing
        secret = secrets.token_urlsafe(32)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        write_synced(tmp, secret.encode(), mode=0o600)
        try:
            if existing is None:
                os.link(tmp, path)
            else:
                os.replace(tmp, path)
        except FileExistsError:
            continue
        finally:
            tmp.unlink(missing_ok=True)
        fsync_dir(path.parent)
        return secret
