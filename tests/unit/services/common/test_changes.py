"""``Changes``: a wait ends on a change made by another thread, never misses one made before
it began, and is bounded in time and in number; closing answers every wait."""

from __future__ import annotations

import threading

import anyio
import pytest

from services.common.changes import Changes, long_poll

pytestmark = pytest.mark.anyio


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"


async def test_a_change_on_another_thread_ends_the_wait() -> None:
    changes = Changes(max_waiters=4)
    seen = changes.version
    timer = threading.Timer(0.2, changes.advance)
    timer.start()
    with anyio.fail_after(10):
        assert await changes.wait_past(seen, 20)
    assert changes.version == seen + 1


async def test_a_change_before_the_wait_is_not_missed() -> None:
    changes = Changes(max_waiters=4)
    seen = changes.version
    await anyio.to_thread.run_sync(changes.advance)
    with anyio.fail_after(1):
        assert await changes.wait_past(seen, 20)


async def test_without_a_change_the_wait_ends_at_its_timeout() -> None:
    changes = Changes(max_waiters=4)
    started = anyio.current_time()
    assert not await changes.wait_past(changes.version, 0.2)
    assert anyio.current_time() - started >= 0.2


async def test_past_max_waiters_a_wait_ends_at_once() -> None:
    changes = Changes(max_waiters=1)
    seen = changes.version
    async with anyio.create_task_group() as tasks:
        tasks.start_soon(changes.wait_past, seen, 20)
        await anyio.sleep(0.05)
        with anyio.fail_after(1):
            assert not await changes.wait_past(seen, 20)
        changes.advance()


async def test_closing_answers_every_wait_and_each_one_after() -> None:
    changes = Changes(max_waiters=4)
    seen = changes.version
    answers: list[bool] = []

    async def wait() -> None:
        answers.append(await changes.wait_past(seen, 20))

    with anyio.fail_after(5):
        async with anyio.create_task_group() as tasks:
            tasks.start_soon(wait)
            tasks.start_soon(wait)
            await anyio.sleep(0.05)
            threading.Thread(target=changes.close).start()
        assert answers == [False, False]
        assert not await changes.wait_past(seen, 20)


async def test_a_long_poll_reads_again_after_each_change_until_its_answer_is_ready() -> None:
    """Changes of anything (another job's progress) wake the poll; it answers only once
    what it reads is ready, and reads nothing more meanwhile."""
    changes = Changes(max_waiters=4)
    state = {"value": 0}
    reads: list[int] = []

    async def read() -> int:
        reads.append(state["value"])
        return state["value"]

    def change_to(value: int) -> None:
        state["value"] = value
        changes.advance()

    for delay, value in ((0.1, 1), (0.2, 2), (0.3, 3)):
        threading.Timer(delay, change_to, (value,)).start()
    with anyio.fail_after(10):
        assert await long_poll(read, lambda value: value >= 3, changes, 20) == 3
    assert reads[0] == 0
    assert reads[-1] == 3
    assert reads == sorted(set(reads))  # a read only after a change


async def test_a_long_poll_answers_as_it_reads_once_its_wait_is_over() -> None:
    changes = Changes(max_waiters=4)

    async def read() -> str:
        return "queued"

    started = anyio.current_time()
    assert await long_poll(read, lambda _: False, changes, 0.2) == "queued"
    assert anyio.current_time() - started >= 0.2
