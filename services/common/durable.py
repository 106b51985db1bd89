"""Durable file writes: what a crash may interrupt, it must not leave half-written.

Every write goes to a temporary file in the same directory, is fsynced, renamed over the
target (atomic on POSIX) and the directory is fsynced so the rename itself survives a crash.
State that changes record by record goes to SQLite instead, opened by ``open_sqlite``.
"""

from __future__ import annotations

import os
import secrets
import sqlite3
from pathlib import Path
from typing import Literal


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


def fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_synced(path: Path, data: bytes, *, mode: int = 0o644) -> None:
    """Write ``path`` and fsync it, in place: for a file that nothing reads until a later
    atomic write (a manifest, say) names it, and that is removed if a crash comes first."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        view = memoryview(data)
        while view:
            written = os.write(fd, view)
            view = view[written:]
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


class AppendLog:
    """An append-only file of lines, fsynced per append: a journal that survives kill -9.

    A torn last line (a crash mid-write) is dropped on read, since it was never acknowledged.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)

    def append(self, line: str) -> None:
        if "\n" in line:
            raise ValueError("a journal line cannot contain a newline")
        os.write(self._fd, (line + "\n").encode())
        os.fsync(self._fd)

    def read_lines(self) -> list[str]:
        data = self.path.read_bytes()
        complete = data[: data.rfind(b"\n") + 1]
        return complete.decode().splitlines()

    def rewrite(self, lines: list[str]) -> None:
        """Compact the log to ``lines`` atomically."""
        atomic_write(self.path, "".join(f"{line}\n" for line in lines).encode(), mode=0o600)
        os.close(self._fd)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)

    def close(self) -> None:
        os.close(self._fd)


def generated_secret(path: Path) -> str:
    """The secret kept in ``path`` (0600), generated and made durable the first time.

    Created with ``O_EXCL``, so two processes starting together agree on one secret.
    """
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return path.read_text().strip()
    secret = secrets.token_urlsafe(32)
    with os.fdopen(fd, "w") as handle:
        handle.write(secret)
        handle.flush()
        os.fsync(handle.fileno())
    fsync_dir(path.parent)
    return secret
