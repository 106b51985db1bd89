"""Turns at costly work: at most ``count`` at once, a turn not had in time refused."""

from __future__ import annotations

from collections.abc import Callable

import anyio
import pytest

from services.common.slots import Slots, SlotsBusy


def test_a_turn_beyond_the_count_is_refused_after_the_wait() -> None:
    slots = Slots("query", 1, 0.1)
    outcome: list[str] = []

    async def hold(held: anyio.Event, release: anyio.Event) -> None:
        async with slots.turn():
            held.set()
            await release.wait()

    async def scenario() -> None:
        held, release = anyio.Event(), anyio.Event()
        async with anyio.create_task_group() as tasks:
            tasks.start_soon(hold, held, release)
            await held.wait()
            assert not slots.idle
            started = anyio.current_time()
            with pytest.raises(SlotsBusy) as busy:
                async with slots.turn():
                    outcome.append("second turn ran")
            outcome.append(f"waited {anyio.current_time() - started >= 0.1}")
            assert str(busy.value) == "all 1 query slots stayed busy for 0.1 s; retry later"
            assert (busy.value.count, busy.value.wait_s) == (1, 0.1)
            release.set()
        assert slots.idle

    anyio.run(scenario)
    assert outcome == ["waited True"]


def test_a_turn_freed_in_time_is_taken_and_freed_even_by_a_failure() -> None:
    slots = Slots("call", 1, 5)
    order: list[str] = []

    async def holder() -> None:
        async with slots.turn():
            order.append("first")
            await anyio.sleep(0.05)

    async def fail_in_a_turn() -> None:
        async with slots.turn():
            order.append("second")
            raise RuntimeError("the work failed")

    async def failing() -> None:
        await anyio.sleep(0.01)
        with pytest.raises(RuntimeError):
            await fail_in_a_turn()

    async def scenario() -> None:
        async with anyio.create_task_group() as tasks:
            tasks.start_soon(holder)
            tasks.start_soon(failing)
        assert slots.idle
        async with slots.turn():
            order.append("third")

    anyio.run(scenario)
    assert order == ["first", "second", "third"]


def test_a_held_slot_is_given_back_once_by_whichever_task_ends_the_work() -> None:
    """A streamed answer takes its slot in the route and gives it back when the server has
    sent it, from another task; a second release must not free someone else's slot."""
    slots = Slots("stream", 1, 0.1)

    async def scenario() -> None:
        release = await slots.hold()
        with pytest.raises(SlotsBusy):
            await slots.hold()
        async with anyio.create_task_group() as tasks:
            tasks.start_soon(_call, release)
        assert slots.idle
        again = await slots.hold()
        release()
        assert not slots.idle
        again()
        assert slots.idle

    anyio.run(scenario)


async def _call(release: Callable[[], None]) -> None:
    release()
