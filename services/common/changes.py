"""``Changes``: a version that worker threads advance and requests wait past on the event loop.

A long poll (Consul's blocking queries, Kafka's fetch wait) answers a reader as soon as
something new is there instead of the reader asking again every few seconds: fresher
answers, and a follower that is idle costs one request every ``wait`` seconds, not one every
poll interval (the ledger's log showed the knowledge follower's read every 2 s, forever).

What advances the version runs on worker threads (the chain's miner, the external node's
follower); the waiters are request handlers on the event loop. A waiter notes the version
before it reads, and waits only while the version is still that one, so nothing that
happened between its read and its wait is missed. Waiting is bounded: at most
``max_waiters`` requests at once (beyond, a request answers at once, as without a wait) and
each for at most the time it asked; ``close`` (the process told to stop) answers every wait
at once, so a long poll never holds a shutdown.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Awaitable, Callable
from typing import TypeVar

import anyio

T = TypeVar("T")


class Changes:
    def __init__(self, max_waiters: int) -> None:
        self.max_waiters = max_waiters
        self._version = 0
        self._closed = False
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._waiters: set[asyncio.Future[None]] = set()

    @property
    def version(self) -> int:
        return self._version

    def advance(self) -> None:
        """Something changed: wake every wait (from any thread). A wait that begins meanwhile
        sees the new version once it is registered, so none is missed when none is woken."""
        with self._lock:
            self._version += 1
        if self._waiters:
            self._wake()

    def close(self) -> None:
        """Answer every wait now and each one after it at once (from any thread, or a signal
        handler on the event loop's)."""
        self._closed = True
        self._wake()

    async def wait_past(self, version: int, timeout_s: float) -> bool:
        """Whether the version moved past ``version`` within ``timeout_s``. False at once
        when closed or when ``max_waiters`` requests already wait."""
        loop = asyncio.get_running_loop()
        self._loop = loop
        if self._version != version:
            return True
        if self._closed or len(self._waiters) >= self.max_waiters:
            return False
        woken: asyncio.Future[None] = loop.create_future()
        self._waiters.add(woken)
        try:
            if self._version == version and not self._closed:
                with anyio.move_on_after(timeout_s):
                    await woken
            return self._version != version
        finally:
            self._waiters.discard(woken)

    def _wake(self) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._wake_waiters)

    def _wake_waiters(self) -> None:
        for woken in self._waiters:
            if not woken.done():
                woken.set_result(None)


async def long_poll(
    read: Callable[[], Awaitable[T]], ready: Callable[[T], bool], changes: Changes, wait_s: float
) -> T:
    """``read``'s answer once ``ready`` holds for it, read again after each change, or its
    answer as it is once ``wait_s`` is over (at once while too many others wait, or once
    ``changes`` is closed)."""
    deadline = anyio.current_time() + wait_s
    while True:
        seen = changes.version
        answer = await read()
        left = deadline - anyio.current_time()
        if ready(answer) or left <= 0 or not await changes.wait_past(seen, left):
            return answer
