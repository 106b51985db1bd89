"""The development faucet's rate limits: once per address per interval, and a global budget.

Funding is a real transaction from the faucet key on the chain (see ``node.py``); this module
only decides whether a request may have one, and when it may try again. The limits live in
memory: a restart forgets them, which on a development chain costs at most one extra grant
per address, and the global budget still bounds how fast the faucet can be drained.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable


class RateLimited(Exception):
    """Refused; ``retry_after_s`` says when the same request would be granted."""

    def __init__(self, message: str, retry_after_s: float) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


class FaucetLimits:
    """Per-address interval and a sliding one-minute window over all addresses."""

    def __init__(
        self,
        per_address_interval_s: float,
        global_per_minute: int,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.interval_s = per_address_interval_s
        self.global_per_minute = global_per_minute
        self.clock = clock
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}
        self._window: deque[float] = deque()

    def acquire(self, address: str) -> None:
        """Record a grant to ``address``, or raise ``RateLimited`` without recording one."""
        with self._lock:
            now = self.clock()
            while self._window and now - self._window[0] >= 60.0:
                self._window.popleft()
            last = self._last.get(address)
            if last is not None and now - last < self.interval_s:
                wait = self.interval_s - (now - last)
                raise RateLimited(f"{address} was funded {now - last:.0f} s ago", wait)
            if len(self._window) >= self.global_per_minute:
                wait = 60.0 - (now - self._window[0])
                raise RateLimited("the faucet's budget for this minute is spent", wait)
            self._last[address] = now
            self._window.append(now)

    def release(self, address: str) -> None:
        """Undo the grant of a request whose transaction failed, so it may retry at once."""
        with self._lock:
            self._last.pop(address, None)
            if self._window:
                self._window.pop()
