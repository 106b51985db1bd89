"""The replay guard: every (address, nonce) seen within the clock window, kept on disk.

A nonce only needs remembering until its request's timestamp falls out of the accepted
window, since a replay after that is rejected for its timestamp anyway. Entries are appended
to a journal (fsynced before the request proceeds), so a restart cannot reopen the window
for a replay; the journal is compacted once most of it has expired.
"""

from __future__ import annotations

import heapq
import threading
import time
from pathlib import Path

from services.common.durable import AppendLog


class NonceStore:
    def __init__(self, path: Path, window_s: int, *, compact_after: int = 10_000) -> None:
        self.window_s = window_s
        self.compact_after = compact_after
        self._log = AppendLog(path)
        self._lock = threading.Lock()
        self._expiry: dict[tuple[str, str], float] = {}
        self._heap: list[tuple[float, str, str]] = []
        self._appended = 0
        now = time.time()
        for line in self._log.read_lines():
            address, nonce, expires = line.split(" ")
            if float(expires) > now:
                self._remember(address, nonce, float(expires))

    def use(self, address: str, nonce: str, timestamp: int) -> bool:
        """Record the nonce; ``False`` if this address already used it within the window."""
        key = (address.lower(), nonce)
        expires = float(timestamp + self.window_s + 1)
        with self._lock:
            self._expire(time.time())
            if key in self._expiry:
                return False
            self._log.append(f"{key[0]} {nonce} {expires:.0f}")
            self._remember(key[0], nonce, expires)
            self._appended += 1
            if self._appended >= self.compact_after and len(self._expiry) < self._appended // 2:
                self._compact()
            return True

    def __len__(self) -> int:
        with self._lock:
            self._expire(time.time())
            return len(self._expiry)

    def close(self) -> None:
        self._log.close()

    def _remember(self, address: str, nonce: str, expires: float) -> None:
        self._expiry[(address, nonce)] = expires
        heapq.heappush(self._heap, (expires, address, nonce))

    def _expire(self, now: float) -> None:
        while self._heap and self._heap[0][0] <= now:
            _, address, nonce = heapq.heappop(self._heap)
            self._expiry.pop((address, nonce), None)

    def _compact(self) -> None:
        lines = [f"{a} {n} {e:.0f}" for (a, n), e in self._expiry.items()]
        self._log.rewrite(lines)
        self._appended = len(lines)
