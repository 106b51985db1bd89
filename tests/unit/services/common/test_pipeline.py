"""A context manager entered and left on worker threads, its exit shielded."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import anyio
import pytest

from services.common.pipeline import entered_in_worker_thread


class Spool:
    """Where and whether a context manager was entered and left, and what it saw leave."""

    def __init__(self, suppress: bool = False) -> None:
        self.suppress = suppress
        self.threads: list[threading.Thread] = []
        self.left_with: list[BaseException | None] = []

    @contextmanager
    def opened(self) -> Iterator[str]:
        self.threads.append(threading.current_thread())
        try:
            yield "spool"
        except Exception as error:
            self.left_with.append(error)
            if not self.suppress:
                raise
        else:
            self.left_with.append(None)
        finally:
            self.threads.append(threading.current_thread())


def test_it_is_entered_and_left_off_the_event_loop() -> None:
    spool = Spool()

    async def use() -> str:
        async with entered_in_worker_thread(spool.opened()) as entered:
            return entered

    assert anyio.run(use) == "spool"
    assert len(spool.threads) == 2
    assert threading.main_thread() not in spool.threads
    assert spool.left_with == [None]


def test_an_error_inside_reaches_the_exit_and_then_the_caller() -> None:
    spool = Spool()

    async def use() -> None:
        async with entered_in_worker_thread(spool.opened()):
            raise ValueError("refused")

    with pytest.raises(ValueError, match="refused"):
        anyio.run(use)
    assert [type(error) for error in spool.left_with] == [ValueError]


def test_an_error_the_exit_suppresses_goes_no_further() -> None:
    spool = Spool(suppress=True)

    async def use() -> str:
        async with entered_in_worker_thread(spool.opened()):
            raise ValueError("refused")
        return "after"

    assert anyio.run(use) == "after"
    assert [type(error) for error in spool.left_with] == [ValueError]


def test_a_cancelled_request_still_leaves_it() -> None:
    """A client gone cancels the request's scope; unshielded, the exit's worker thread was
    never started and the spool stayed until a restart."""
    spool = Spool()

    async def use() -> None:
        with anyio.move_on_after(0.05):
            async with entered_in_worker_thread(spool.opened()):
                await anyio.sleep(10)

    anyio.run(use)
    assert len(spool.threads) == 2
    assert threading.main_thread() not in spool.threads
