"""The replay guard: every (address, nonce) seen within the clock window, kept on disk.

A nonce only needs remembering until its request's timestamp falls out of the accepted
window, since a replay after that is rejected for its timestamp anyway. Entries are appended
to a journal (fsynced before the request proceeds), so a restart cannot reopen the window
for a replay; the journal is compacted once most of it has expired.

The store holds at most ``max_entries`` live nonces. When it is full a new nonce is refused
(:class:`NonceStoreFull`, answered 503 with ``Retry-After``) rather than an old one forgotten,
since forgetting a live nonce would let its request be replayed. Without a bound one client
signing 760 requests a second grew it by 180 MB of memory and 40 MB of journal per window.

One address holds at most ``max_per_address`` of them (:class:`NonceQuotaExceeded`, answered
429): with the whole store as its only bound, one approved robot signing as fast as it could
filled it and refused every other robot's writes for the rest of the window.
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

from services.common.durable import AppendLog

log = logging.getLogger("robocloud.nonces")

MAX_LIVE_NONCES = 200_000
"""The default bound on live nonces: about 80 MB of memory (some 400 bytes an entry) and
18 MB of journal at worst. A nonce lives about ``window_s`` (300 s by default) past a
current timestamp, so this admits some 650 signed writes a second, sustained, to one service:
more than one service's fsynced journal and routes take."""


MAX_LIVE_NONCES_PER_ADDRESS = MAX_LIVE_NONCES // 8
"""One address's share: some 80 signed writes a second, sustained over the window; it takes
eight robots at that rate, not one, to fill the store."""


class NonceQuotaExceeded(Exception):
    """This address holds its share of live nonces; its oldest expires ``retry_after_s``
    from now."""

    def __init__(self, address: str, limit: int, retry_after_s: float) -> None:
        super().__init__(f"{address} holds its limit of {limit} live nonces")
        self.address = address
        self.limit = limit
        self.retry_after_s = retry_after_s


class NonceStoreFull(Exception):
    """No room for another live nonce until the oldest expires, ``retry_after_s`` from now."""

    def __init__(self, limit: int, retry_after_s: float) -> None:
        super().__init__(f"the replay guard holds its limit of {limit} live nonces")
        self.limit = limit
        self.retry_after_s = retry_after_s


class NonceStore:
    def __init__(
        self,
        path: Path,
        window_s: int,
        *,
        compact_after: int = 10_000,
        max_entries: int = MAX_LIVE_NONCES,
        max_per_address: int = MAX_LIVE_NONCES_PER_ADDRESS,
    ) -> None:
        self.window_s = window_s
        self.compact_after = compact_after
        self.max_entries = max_entries
        self.max_per_address = max_per_address
        self._log = AppendLog(path)
        self._lock = threading.Lock()
        self._expiry: dict[tuple[str, str], float] = {}
        self._heap: list[tuple[float, str, str]] = []
        self._by_address: dict[str, list[float]] = {}
        """Each address's live expiries, a heap: its count and its oldest."""
        self._appended = 0
        now = time.time()
        for line in self._log.read_lines():
            address, nonce, expires = line.split(" ")
            if float(expires) > now:
                self._remember(address, nonce, float(expires))

    def use(self, address: str, nonce: str, timestamp: int) -> bool:
        """Record the nonce; ``False`` if this address already used it within the window.

        Raises :class:`NonceQuotaExceeded` when the address holds ``max_per_address`` live
        nonces, :class:`NonceStoreFull` when ``max_entries`` are live, recording nothing.
        """
        key = (address.lower(), nonce)
        expires = float(timestamp + self.window_s + 1)
        with self._lock:
            now = time.time()
            self._expire(now)
            if key in self._expiry:
                return False
            held = self._by_address.get(key[0], [])
            if len(held) >= self.max_per_address:
                raise NonceQuotaExceeded(address, self.max_per_address, held[0] - now)
            if len(self._expiry) >= self.max_entries:
                raise NonceStoreFull(self.max_entries, self._heap[0][0] - now)
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
        heapq.heappush(self._by_address.setdefault(address, []), expires)

    def _expire(self, now: float) -> None:
        """Forget what expired. The store's heap gives entries up in order of expiry, so each
        is the oldest of its address's too."""
        while self._heap and self._heap[0][0] <= now:
            _, address, nonce = heapq.heappop(self._heap)
            self._expiry.pop((address, nonce), None)
            held = self._by_address[address]
            heapq.heappop(held)
            if not held:
                del self._by_address[address]

    def _compact(self) -> None:
        """Rewrite the journal with the live nonces. A rewrite that fails (a full disk) is
        logged and tried again after as many appends: the nonce that triggered it is already
        durable, and raising failed that request and every signed request after it."""
        lines = [f"{a} {n} {e:.0f}" for (a, n), e in self._expiry.items()]
        try:
            self._log.rewrite(lines)
        except OSError as exc:
            log.warning("nonce journal not compacted", extra={"error": str(exc)})
            self._appended = len(self._expiry)
            return
        self._appended = len(lines)


MAX_STRANGER_NONCES = 50_000
"""Refused strangers' nonces held at once: some 20 MB at worst (each its own address and a
64-character nonce; 13.7 MB measured with 32-character ones)."""


class StrangerNonces:
    """Nonces of requests refused because the registry had no record of their signer (403
    ``address_not_allowed``), held in memory only until their timestamp leaves the window.

    Such a request uses no nonce of the store, since self-made keys cost nothing and their
    journal lines would fill it. Without this, a copy of one succeeded once if its key was
    registered and approved within the clock window, after its robot had moved on. Past
    ``limit`` the oldest goes, so a flood of strangers pushes out each other's and nobody is
    refused for it; a restart forgets them all.
    """

    def __init__(
        self,
        window_s: int,
        limit: int = MAX_STRANGER_NONCES,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.window_s = window_s
        self.limit = limit
        self.clock = clock
        self._expiry: OrderedDict[tuple[str, str], float] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._expiry)

    def remember(self, address: str, nonce: str, timestamp: int) -> None:
        with self._lock:
            self._expiry[address, nonce] = timestamp + self.window_s
            self._expiry.move_to_end((address, nonce))
            now = self.clock()
            while self._expiry and (
                len(self._expiry) > self.limit or next(iter(self._expiry.values())) < now
            ):
                self._expiry.popitem(last=False)

    def refused(self, address: str, nonce: str) -> bool:
        """Whether a request of ``address`` with ``nonce`` was refused as a stranger's."""
        with self._lock:
            return self._expiry.get((address, nonce), 0.0) >= self.clock()
