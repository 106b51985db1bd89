"""A reentrant lock handed to its waiters in the order they came.

Python's locks promise no order: a thread that releases a lock and takes it again at once
usually wins it back from a thread that has been waiting all along, since the waiter must
first be woken and then get the interpreter. The ledger's miner does exactly that between
the blocks of a sender's waiting transactions, and every read of the chain waits on the same
lock; here a release hands the lock to the longest waiter directly, so a thread that asks
again queues behind everyone already waiting.
"""

from __future__ import annotations

import threading
from collections import deque
from types import TracebackType


class FairLock:
    """A reentrant FIFO lock: ``with lock:`` as with ``threading.RLock``."""

    def __init__(self) -> None:
        self._state = threading.Lock()
        self._owner: int | None = None
        self._depth = 0
        self._waiters: deque[tuple[int, threading.Lock]] = deque()

    def acquire(self) -> None:
        me = threading.get_ident()
        with self._state:
            if self._owner == me:
                self._depth += 1
                return
            if self._owner is None:
                self._owner, self._depth = me, 1
                return
            turn = threading.Lock()
            turn.acquire()
            self._waiters.append((me, turn))
        try:
            turn.acquire()  # released by the holder that made this thread the owner
        except BaseException:
            self._withdraw(me, turn)
            raise

    def release(self) -> None:
        with self._state:
            if self._owner != threading.get_ident():
                raise RuntimeError("cannot release a FairLock this thread does not hold")
            self._depth -= 1
            if self._depth:
                return
            self._hand_over()

    def _hand_over(self) -> None:
        """Make the longest waiter the owner (the state lock is held)."""
        if self._waiters:
            self._owner, turn = self._waiters.popleft()
            self._depth = 1
            turn.release()
        else:
            self._owner = None

    def _withdraw(self, me: int, turn: threading.Lock) -> None:
        """Leave the queue after an interrupted wait, or pass on a turn that came anyway."""
        with self._state:
            if (me, turn) in self._waiters:
                self._waiters.remove((me, turn))
            elif self._owner == me:
                self._hand_over()

    def __enter__(self) -> FairLock:
        self.acquire()
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        value: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.release()
