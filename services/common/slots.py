"""Turns at costly work that strangers may ask for free, waited for on the event loop.

A service runs blocking work on anyio's worker threads (40 of them), which every route shares,
and all of them share one GIL with the event loop. Work a stranger may ask for without paying
(an ``eth_call`` that loops to the EVM timeout, a records query that scans a million
documents) must therefore not run as often as it is asked: forty such requests at once held
every thread, and a read or a write behind them waited for seconds or timed out.

``Slots`` lets ``count`` of them run at a time (more buy no throughput under the GIL). A
request waits for its turn on the event loop, where waiting holds no thread, for at most
``wait_s``, then ``SlotsBusy`` refuses it; everything else keeps the threads to itself.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import TypeVar

import anyio

T = TypeVar("T")


class SlotsBusy(Exception):
    """Every slot stayed busy for the whole wait."""

    def __init__(self, kind: str, count: int, wait_s: float) -> None:
        super().__init__(f"all {count} {kind} slots stayed busy for {wait_s:g} s; retry later")
        self.count = count
        self.wait_s = wait_s


class Slots:
    """At most ``count`` turns at once at ``kind`` work (``call``, ``query``: for messages);
    a turn not had within ``wait_s`` is refused."""

    def __init__(self, kind: str, count: int, wait_s: float) -> None:
        self.kind = kind
        self.count = count
        self.wait_s = wait_s
        self._limiter = anyio.CapacityLimiter(count)

    @property
    def idle(self) -> bool:
        """No turn is being taken: nothing costly is running."""
        return self._limiter.borrowed_tokens == 0

    @asynccontextmanager
    async def turn(self) -> AsyncIterator[None]:
        """Hold one slot for the body of the ``async with``; ``SlotsBusy`` if none came."""
        release = await self.hold()
        try:
            yield
        finally:
            release()

    async def hold(self) -> Callable[[], None]:
        """Take one slot for work that outlives the calling task (a streamed answer, which
        the server sends after the route returned); the function returned gives it back,
        once, whoever calls it. ``SlotsBusy`` if no slot came."""
        holder = object()
        try:
            with anyio.fail_after(self.wait_s):
                await self._limiter.acquire_on_behalf_of(holder)
        except TimeoutError:
            raise SlotsBusy(self.kind, self.count, self.wait_s) from None
        held = [holder]

        def release() -> None:
            if held:
                self._limiter.release_on_behalf_of(held.pop())

        return release

    async def run_sync(self, work: Callable[[], T]) -> T:
        """``work`` on a worker thread, in a turn: how every route runs its costly work."""
        async with self.turn():
            return await anyio.to_thread.run_sync(work)
