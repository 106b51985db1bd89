"""The development faucet's rate limits: once per address per interval, and a global budget.

Funding is a real transaction from the faucet key on the chain (see ``node.py``); this module
only decides whether a request may have one, and when it may try again. Each address's last
grant is kept in a small SQLite table beside the chain, so a restart does not hand out a second
grant inside the interval; a write whose commit failed (the disk refused its fsync) is voided
at once (``void_failed_commit``), so a restart never finds a grant, or a release, that was
answered as failed. The one-minute global window stays in memory: it only bounds how
fast the faucet can be drained, and a restart takes longer than a fraction of that minute.
Times are wall-clock seconds, because they must mean the same thing after a restart.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

from services.common.durable import open_sqlite, void_failed_commit

GRANTS_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS grants (address TEXT PRIMARY KEY, granted_at REAL NOT NULL)"
)


class RateLimited(Exception):
    """Refused; ``retry_after_s`` says when the same request for ``address`` would be granted."""

    def __init__(self, address: str, reason: str, retry_after_s: float) -> None:
        super().__init__(f"faucet rate limit: {reason}")
        self.address = address
        self.retry_after_s = retry_after_s


class FaucetLimits:
    """Per-address interval (durable in ``path``) and a sliding one-minute window."""

    def __init__(
        self,
        path: Path,
        per_address_interval_s: float,
        global_per_minute: int,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.interval_s = per_address_interval_s
        self.global_per_minute = global_per_minute
        self.clock = clock
        self._lock = threading.Lock()
        self._db = open_sqlite(path, GRANTS_SCHEMA, synchronous="FULL")
        expired = self.clock() - per_address_interval_s
        self._write("DELETE FROM grants WHERE granted_at < ?", (expired,))
        rows = self._db.execute("SELECT address, granted_at FROM grants")
        self._last: dict[str, float] = dict(rows)
        self._window: deque[float] = deque()

    def _write(self, statement: str, parameters: tuple[object, ...]) -> None:
        """Run one write, committed on its own. One whose commit fails raises, and its frames,
        commit marker included, may be in the write-ahead log already: voided at once, or a
        restart before the next write recovered it (a grant whose acquire raised refused its
        unfunded robot for the whole interval)."""
        try:
            self._db.execute(statement, parameters)
        except sqlite3.Error:
            void_failed_commit(self._db)
            raise

    def acquire(self, address: str) -> None:
        """Record a grant to ``address``, or raise ``RateLimited`` without recording one; a
        grant the disk fails to record raises too, and no restart finds it."""
        with self._lock:
            now = self.clock()
            while self._window and now - self._window[0] >= 60.0:
                self._window.popleft()
            last = self._last.get(address)
            if last is not None and now - last < self.interval_s:
                wait = self.interval_s - (now - last)
                raise RateLimited(address, f"{address} was funded {now - last:.0f} s ago", wait)
            if len(self._window) >= self.global_per_minute:
                wait = 60.0 - (now - self._window[0])
                raise RateLimited(address, "the faucet's budget for this minute is spent", wait)
            self._write(
                "INSERT OR REPLACE INTO grants (address, granted_at) VALUES (?, ?)", (address, now)
            )
            self._last[address] = now
            self._window.append(now)

    def release(self, address: str) -> None:
        """Undo the grant of a request whose transaction failed, so it may retry at once; its
        own place in the minute's budget is given back, not the newest grant's. A release the
        disk fails to record raises and the grant stays, here and after a restart."""
        with self._lock:
            self._write("DELETE FROM grants WHERE address = ?", (address,))
            granted_at = self._last.pop(address, None)
            if granted_at is not None and granted_at in self._window:
                self._window.remove(granted_at)

    def close(self) -> None:
        with self._lock:
            self._db.close()
