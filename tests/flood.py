"""Strangers asking for costly work again and again, while a test checks what others get."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Generic, TypeVar

import httpx

T = TypeVar("T")


class Flood(Generic[T]):
    """The answers the flooding clients got so far, and whether they all still run."""

    def __init__(self) -> None:
        self.answers: list[T] = []
        self.threads: list[threading.Thread] = []

    def running(self) -> bool:
        """Every client is still sending: none failed (a timeout, a refused connection)."""
        return all(thread.is_alive() for thread in self.threads)


FLOODER = "127.0.0.2"
"""Where floods come from: one client, and not the test's own (127.0.0.1), which a service
counts as another client with its own share of the turns at costly work."""


@contextmanager
def flooding(send: Callable[[httpx.Client], T], clients: int) -> Iterator[Flood[T]]:
    """``clients`` threads, each with its own connection from ``FLOODER``, calling ``send``
    over and over until the block ends; each finishes the request it has in flight before
    stopping."""
    flood: Flood[T] = Flood()
    stop = threading.Event()

    def run() -> None:
        from_flooder = httpx.HTTPTransport(local_address=FLOODER)
        with httpx.Client(transport=from_flooder, timeout=120) as client:
            while not stop.is_set():
                flood.answers.append(send(client))

    flood.threads = [threading.Thread(target=run) for _ in range(clients)]
    for thread in flood.threads:
        thread.start()
    try:
        yield flood
    finally:
        stop.set()
        for thread in flood.threads:
            thread.join()
