"""Turns at costly work that strangers may ask for free, waited for on the event loop, and
shared out between the clients asking.

A service runs blocking work on anyio's worker threads (40 of them), which every route shares,
and all of them share one GIL with the event loop. Work a stranger may ask for without paying
(an ``eth_call`` that loops to the EVM timeout, a records query that scans a million
documents) must therefore not run as often as it is asked: forty such requests at once held
every thread, and a read or a write behind them waited for seconds or timed out.

``Slots`` lets ``count`` of them run at a time (more buy no throughput under the GIL). A
request waits for its turn on the event loop, where waiting holds no thread, for at most
``wait_s``, then ``SlotsBusy`` refuses it; everything else keeps the threads to itself.

One client holds at most ``share`` of the turns (half of them), as nginx's ``limit_conn``
bounds the connections of one address: a client asking for more waits for one of its own
turns to end, behind nobody else, and is refused with ``ShareBusy`` when none did in time.
Before, one client flooding slow SPARQL queries, looping calls or stalled downloads took every
turn for as long as it kept asking, and every other client got ``busy``. A client is the
address the request came from (``client_var``, set by the request layers): an IPv4 address,
or an IPv6 /64, which one host usually has whole. Work with no client (the service's own)
takes turns without a share.
"""

from __future__ import annotations

import ipaddress
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import TypeVar

import anyio

T = TypeVar("T")

client_var: ContextVar[str | None] = ContextVar("client", default=None)
"""Who is asking, for the shares: ``client_key`` of the request's peer address."""


def client_key(host: str) -> str:
    """The client a peer address counts as: an IPv4 address (an IPv4-mapped IPv6 one too),
    the /64 of an IPv6 one, any other name (a Unix socket's) as it is."""
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return host
    if isinstance(address, ipaddress.IPv6Address):
        if address.ipv4_mapped is not None:
            return str(address.ipv4_mapped)
        return str(ipaddress.IPv6Network((address, 64), strict=False))
    return str(address)


class SlotsBusy(Exception):
    """Every slot stayed busy for the whole wait."""

    def __init__(self, kind: str, count: int, wait_s: float, message: str | None = None) -> None:
        super().__init__(
            message or f"all {count} {kind} slots stayed busy for {wait_s:g} s; retry later"
        )
        self.count = count
        self.wait_s = wait_s


class ShareBusy(SlotsBusy):
    """The client already held its share of the slots for the whole wait."""

    def __init__(self, kind: str, count: int, share: int, wait_s: float) -> None:
        super().__init__(
            kind,
            count,
            wait_s,
            f"this client already holds {share} of the {count} {kind} slots, its share, and "
            f"none came free in {wait_s:g} s; retry later",
        )
        self.share = share


@dataclass
class _Share:
    """One client's turns: its limiter, and how many of its requests hold or await one (the
    entry is forgotten when none does, so only clients with business are kept)."""

    limiter: anyio.CapacityLimiter
    users: int = 0


class Slots:
    """At most ``count`` turns at once at ``kind`` work (``call``, ``query``: for messages),
    at most ``share`` of them a client's; a turn not had within ``wait_s`` is refused."""

    def __init__(self, kind: str, count: int, wait_s: float) -> None:
        self.kind = kind
        self.count = count
        self.share = max(1, count // 2)
        self.wait_s = wait_s
        self._limiter = anyio.CapacityLimiter(count)
        self._shares: dict[str, _Share] = {}

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
        once, whoever calls it. ``ShareBusy`` if the client's share stayed taken,
        ``SlotsBusy`` if no slot came."""
        client = client_var.get()
        holder = object()
        share = self._enter(client)
        had_share = False
        try:
            with anyio.fail_after(self.wait_s):
                if share is not None:
                    await share.limiter.acquire_on_behalf_of(holder)
                had_share = True
                await self._limiter.acquire_on_behalf_of(holder)
        except BaseException as failure:
            self._leave(client, share, holder if had_share else None)
            if not isinstance(failure, TimeoutError):
                raise
            if had_share:
                raise SlotsBusy(self.kind, self.count, self.wait_s) from None
            raise ShareBusy(self.kind, self.count, self.share, self.wait_s) from None
        held = [holder]

        def release() -> None:
            if held:
                self._limiter.release_on_behalf_of(held[0])
                self._leave(client, share, held.pop())

        return release

    async def run_sync(self, work: Callable[[], T]) -> T:
        """``work`` on a worker thread, in a turn: how every route runs its costly work."""
        async with self.turn():
            return await anyio.to_thread.run_sync(work)

    def _enter(self, client: str | None) -> _Share | None:
        if client is None:
            return None
        share = self._shares.get(client)
        if share is None:
            share = self._shares[client] = _Share(anyio.CapacityLimiter(self.share))
        share.users += 1
        return share

    def _leave(self, client: str | None, share: _Share | None, holder: object | None) -> None:
        if client is None or share is None:
            return
        if holder is not None:
            share.limiter.release_on_behalf_of(holder)
        share.users -= 1
        if share.users == 0:
            del self._shares[client]
