"""Turns at costly work: at most ``count`` at once and ``share`` of them a client's, a turn not
had in time refused."""

from __future__ import annotations

from collections.abc import Awaitable, Callable

import anyio
import pytest

from services.common.slots import ShareBusy, Slots, SlotsBusy, client_key, client_var


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


def _as(client: str | None, slots: Slots) -> Callable[[], Awaitable[Callable[[], None]]]:
    """``slots.hold`` as a request from ``client`` takes it (the request layers set the
    client)."""

    async def hold() -> Callable[[], None]:
        token = client_var.set(client)
        try:
            return await slots.hold()
        finally:
            client_var.reset(token)

    return hold


def test_one_client_holds_at_most_its_share_and_others_get_the_rest() -> None:
    slots = Slots("query", 4, 0.1)
    assert slots.share == 2

    async def scenario() -> None:
        flooder = _as("192.0.2.7", slots)
        held = [await flooder(), await flooder()]
        with pytest.raises(ShareBusy) as refused:
            await flooder()
        assert str(refused.value) == (
            "this client already holds 2 of the 4 query slots, its share, and none came free "
            "in 0.1 s; retry later"
        )
        assert (refused.value.share, refused.value.count, refused.value.wait_s) == (2, 4, 0.1)
        others = [await _as("192.0.2.8", slots)(), await _as("198.51.100.1", slots)()]
        with pytest.raises(SlotsBusy) as busy:
            await _as("203.0.113.9", slots)()
        assert not isinstance(busy.value, ShareBusy)
        for release in held + others:
            release()
        assert slots.idle

    anyio.run(scenario)


def test_a_client_over_its_share_waits_behind_its_own_turns_only() -> None:
    slots = Slots("SPARQL", 2, 5)
    order: list[str] = []

    async def ask(client: str, name: str, seconds: float) -> None:
        release = await _as(client, slots)()
        order.append(f"{name} started")
        await anyio.sleep(seconds)
        release()

    async def scenario() -> None:
        async with anyio.create_task_group() as tasks:
            tasks.start_soon(ask, "192.0.2.7", "flooder 1", 0.2)
            await anyio.sleep(0.01)
            tasks.start_soon(ask, "192.0.2.7", "flooder 2", 0.01)
            await anyio.sleep(0.01)
            tasks.start_soon(ask, "192.0.2.8", "other", 0.01)
        assert slots.idle

    anyio.run(scenario)
    assert order == ["flooder 1 started", "other started", "flooder 2 started"]


def test_work_with_no_client_takes_turns_without_a_share() -> None:
    slots = Slots("call", 2, 0.1)

    async def scenario() -> None:
        own = [await _as(None, slots)(), await _as(None, slots)()]
        with pytest.raises(SlotsBusy) as busy:
            await _as(None, slots)()
        assert not isinstance(busy.value, ShareBusy)
        for release in own:
            release()

    anyio.run(scenario)


def test_a_client_that_went_away_frees_its_share_for_its_next_request() -> None:
    """A request cancelled while it waits for its share (its client gone) takes no share
    with it: the client's next request gets the turn its finished one gave back, and once
    the client has no turn and waits for none the service keeps nothing for it."""
    slots = Slots("stream", 2, 5)

    async def scenario() -> None:
        flooder = _as("192.0.2.7", slots)
        first = await flooder()
        with anyio.move_on_after(0.05):
            await flooder()
        first()
        again = await flooder()
        again()
        assert slots.idle
        assert not slots._shares  # nothing kept for clients with no turn and no wait

    anyio.run(scenario)


@pytest.mark.parametrize(
    ("peer", "client"),
    [
        ("192.0.2.7", "192.0.2.7"),
        ("2001:db8:1:2:aaaa::1", "2001:db8:1:2::/64"),
        ("2001:db8:1:2:bbbb::9", "2001:db8:1:2::/64"),
        ("::ffff:192.0.2.7", "192.0.2.7"),
        ("/run/robocloud.sock", "/run/robocloud.sock"),
    ],
)
def test_a_client_is_an_ipv4_address_or_an_ipv6_64(peer: str, client: str) -> None:
    assert client_key(peer) == client
