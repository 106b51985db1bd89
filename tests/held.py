"""What a service answers while one of its requests is held in a slow call (a parse, a disk
write, a lock): a call held on the event loop holds every route; one on a thread holds its
own request alone."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Awaitable, Callable
from typing import ParamSpec, TypeVar

import httpx
from starlette.types import ASGIApp, Receive, Scope, Send

from robocloud.signing import VerifiedRequest

P = ParamSpec("P")
T = TypeVar("T")

HOLD_S = 10.0
"""How long a held call waits to be released before it gives up and goes on."""


class Gate:
    """Holds the first call through it until :meth:`release`, or :data:`HOLD_S`."""

    def __init__(self) -> None:
        self.entered = threading.Event()
        self.released = threading.Event()
        self.gave_up = threading.Event()

    def hold(self) -> None:
        """Hold the caller, if it is the first; later callers pass."""
        if self.entered.is_set():
            return
        self.entered.set()
        if not self.released.wait(HOLD_S):
            self.gave_up.set()

    def wrap(self, function: Callable[P, T]) -> Callable[P, T]:
        """``function``, its first call held."""

        def held(*args: P.args, **kwargs: P.kwargs) -> T:
            self.hold()
            return function(*args, **kwargs)

        return held

    def release(self) -> None:
        self.released.set()

    @property
    def holding(self) -> bool:
        """A call is held now: entered, neither released nor given up."""
        return self.entered.is_set() and not (self.released.is_set() or self.gave_up.is_set())


async def answered_while_held(
    gate: Gate,
    held: Awaitable[httpx.Response],
    probes: dict[str, Callable[[], Awaitable[httpx.Response]]],
) -> tuple[httpx.Response, dict[str, httpx.Response], dict[str, bool]]:
    """Send ``held``, and once ``gate`` holds it, :func:`probed`: the held request's answer,
    the probes' answers, and whether each was answered while the gate held. The loop runs
    nothing else while a call on it is held, so neither the wait for the gate nor a probe
    goes on until it gives up."""
    pending = asyncio.ensure_future(held)
    while not gate.entered.is_set():
        assert not pending.done(), f"the held request was answered first: {pending.result()}"
        await asyncio.sleep(0.01)
    answers, answered_while = await probed(gate, probes)
    return await pending, answers, answered_while


async def probed(
    gate: Gate, probes: dict[str, Callable[[], Awaitable[httpx.Response]]]
) -> tuple[dict[str, httpx.Response], dict[str, bool]]:
    """Send each of ``probes`` at once, then release ``gate``: their answers, and whether
    each came while the gate held its call."""
    answered_while: dict[str, bool] = {}

    async def probe(name: str, send: Callable[[], Awaitable[httpx.Response]]) -> httpx.Response:
        response = await send()
        answered_while[name] = gate.holding
        return response

    try:
        answers = await asyncio.gather(*(probe(name, send) for name, send in probes.items()))
    finally:
        gate.release()
    return dict(zip(probes, answers, strict=True)), answered_while


def signed_by(app: ASGIApp, verified: VerifiedRequest) -> ASGIApp:
    """``app`` with every request's signature taken as verified (the guard's part), for a
    route's router served in process."""

    async def signed(scope: Scope, receive: Receive, send: Send) -> None:
        scope.setdefault("state", {})["signature"] = verified
        await app(scope, receive, send)

    return signed
