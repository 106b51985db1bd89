"""Transactions waiting for their sender's nonce gap to close, as anvil and geth queue them.

The chain mines a transaction the moment its nonce is the sender's next one; one with a
higher nonce waits here until the transactions before it arrive (a client sending several
at once cannot control the order they reach the node in). The queue is memory a stranger
fills, so it is bounded per sender and in total, and a transaction waits at most
``timeout_s``; it is not durable (geth journals only its own node's transactions): a
restart drops what was waiting, and its sender sends it again.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from eth.abc import SignedTransactionAPI

from services.ledger.refusals import ChainError
from services.ledger.validation import Fees

PRICE_BUMP_PERCENT = 10
"""A waiting transaction is replaced only by one paying 10 % more (geth's ``PriceBump``)."""


@dataclass(frozen=True)
class PoolLimits:
    max_per_sender: int = 64
    max_total: int = 1024
    timeout_s: float = 3 * 3600.0


@dataclass(frozen=True)
class Waiting:
    transaction: SignedTransactionAPI
    deadline: float


class PendingPool:
    """Future-nonce transactions by sender; changed under the chain's lock only.

    ``find`` alone may be called without the lock (a dict lookup is atomic in CPython): a
    robot polling for the receipt of a waiting transaction is answered null on the event
    loop, without queueing for the lock behind the blocks being mined.
    """

    def __init__(self, limits: PoolLimits, clock: Callable[[], float] = time.monotonic) -> None:
        self.limits = limits
        self._clock = clock
        self._by_sender: dict[bytes, dict[int, Waiting]] = {}
        self._by_hash: dict[bytes, SignedTransactionAPI] = {}

    def __len__(self) -> int:
        return len(self._by_hash)

    def waiting(self, sender: bytes) -> int:
        return len(self._by_sender.get(sender, {}))

    def find(self, tx_hash: bytes) -> SignedTransactionAPI | None:
        """The waiting transaction of that hash (one that has expired is found until the
        next ``expire``)."""
        return self._by_hash.get(tx_hash)

    def add(self, transaction: SignedTransactionAPI) -> None:
        """Queue ``transaction`` (already valid but for its nonce), or refuse it as geth
        does: ``already known``, ``replacement transaction underpriced``,
        ``txpool is full``."""
        self.expire()
        sender = transaction.sender
        queue = self._by_sender.get(sender, {})
        existing = queue.get(transaction.nonce)
        if existing is not None:
            if existing.transaction.hash == transaction.hash:
                raise ChainError("already known")
            old, new = Fees.of(existing.transaction), Fees.of(transaction)
            bump = 100 + PRICE_BUMP_PERCENT
            if new.cap * 100 < old.cap * bump or new.tip * 100 < old.tip * bump:
                raise ChainError("replacement transaction underpriced")
        elif len(queue) >= self.limits.max_per_sender:
            raise ChainError(
                f"txpool is full: address 0x{sender.hex()} has {len(queue)} transactions "
                f"waiting for a nonce gap to close (limit {self.limits.max_per_sender})"
            )
        elif len(self) >= self.limits.max_total:
            raise ChainError(
                f"txpool is full: {len(self)} transactions waiting (limit {self.limits.max_total})"
            )
        if existing is not None:
            del self._by_hash[existing.transaction.hash]
        queue[transaction.nonce] = Waiting(transaction, self._clock() + self.limits.timeout_s)
        self._by_sender[sender] = queue
        self._by_hash[transaction.hash] = transaction

    def take(self, sender: bytes, nonce: int) -> SignedTransactionAPI | None:
        """The waiting transaction with ``sender``'s next ``nonce``, removed from the pool;
        those with lower nonces can never be mined and are dropped."""
        queue = self._by_sender.get(sender)
        if not queue:
            return None
        for stale in [n for n in queue if n < nonce]:
            del self._by_hash[queue.pop(stale).transaction.hash]
        found = queue.pop(nonce, None)
        if found is not None:
            del self._by_hash[found.transaction.hash]
        if not queue:
            del self._by_sender[sender]
        return found.transaction if found is not None else None

    def expire(self) -> None:
        now = self._clock()
        for sender in list(self._by_sender):
            queue = self._by_sender[sender]
            for nonce in [n for n, waiting in queue.items() if waiting.deadline < now]:
                del self._by_hash[queue.pop(nonce).transaction.hash]
            if not queue:
                del self._by_sender[sender]
