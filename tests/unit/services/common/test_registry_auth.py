"""The registry authorizer's cache: bounded, and what it drops is what was used least lately."""

from __future__ import annotations

import anyio

from robocloud.ledger.models import RegisteredRobot
from services.common.registry_auth import RegistryAuthorizer


class CountingAuthorizer(RegistryAuthorizer):
    """Answers "not registered" without a ledger, counting the lookups that missed the cache."""

    def __init__(self, max_cached: int) -> None:
        super().__init__("http://127.0.0.1:9", clock=lambda: 0.0, max_cached=max_cached)
        self.fetched: list[str] = []

    async def _fetch(self, address: str) -> RegisteredRobot | None:
        self.fetched.append(address)
        return None


def look_up(authorizer: RegistryAuthorizer, *addresses: str) -> None:
    async def run() -> None:
        for address in addresses:
            await authorizer.robot(address)

    anyio.run(run)


def test_a_full_cache_drops_the_least_recently_used_address_only() -> None:
    """Before, the 10,001st address emptied the cache, and every robot's next write asked
    the ledger again."""
    authorizer = CountingAuthorizer(max_cached=3)
    look_up(authorizer, "a", "b", "c", "a", "d")
    assert authorizer.fetched == ["a", "b", "c", "d"]
    look_up(authorizer, "a", "c", "d")
    assert authorizer.fetched == ["a", "b", "c", "d"], "recent addresses stayed cached"
    look_up(authorizer, "b")
    assert authorizer.fetched == ["a", "b", "c", "d", "b"], "b was the least recently used"
    authorizer.close()


def test_a_stream_of_one_off_addresses_does_not_push_out_a_robot_that_keeps_writing() -> None:
    authorizer = CountingAuthorizer(max_cached=100)
    for i in range(1_000):
        look_up(authorizer, "robot", f"stranger-{i}")
    assert authorizer.fetched.count("robot") == 1
    look_up(authorizer, "stranger-999", "stranger-0")
    assert authorizer.fetched[-1001:] == [*(f"stranger-{i}" for i in range(1_000)), "stranger-0"]
    authorizer.close()
