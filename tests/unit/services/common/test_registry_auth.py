"""The registry authorizer's cache: bounded, and what it drops is what was used least lately."""

from __future__ import annotations

import anyio
import pytest

from robocloud.ledger.models import RegisteredRobot
from services.common.errors import Forbidden
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


class LedgerOfOneRobot(RegistryAuthorizer):
    """Answers with ``record``, which a test changes as the ledger would, on a clock it
    moves."""

    def __init__(self, record: RegisteredRobot) -> None:
        self.now = 100.0
        super().__init__("http://127.0.0.1:9", clock=lambda: self.now)
        self.record: RegisteredRobot | None = record
        self.fetches = 0

    async def _fetch(self, address: str) -> RegisteredRobot | None:
        self.fetches += 1
        return self.record


def robot_record(roles: tuple[str, ...] = (), active: bool = True) -> RegisteredRobot:
    return RegisteredRobot(
        address="0x" + "ab" * 20,
        metadata_cid=None,
        metadata_hex="0x",
        registered_at=1,
        active=active,
        suspended=False,
        roles=roles,
    )


def authorize(authorizer: RegistryAuthorizer, role: str | None = None) -> None:
    anyio.run(authorizer.authorize, "0x" + "ab" * 20, role)


def test_a_role_granted_after_a_refusal_counts_within_the_refusals_cache_time() -> None:
    """The robot's record was cached ten seconds by the refused request, so a reviewer
    granted the role at once (`admin grant ... reviewer` after `role_required`) was refused
    again for the rest of those ten seconds."""
    authorizer = LedgerOfOneRobot(robot_record())
    with pytest.raises(Forbidden) as refused:
        authorize(authorizer, "reviewer")
    assert refused.value.code == "role_required"
    authorizer.record = robot_record(roles=("reviewer",))
    authorizer.now += 1
    with pytest.raises(Forbidden):
        authorize(authorizer, "reviewer")
    authorizer.now += 1.5
    authorize(authorizer, "reviewer")
    fetches = authorizer.fetches
    authorize(authorizer)
    authorize(authorizer, "reviewer")
    assert authorizer.fetches == fetches, "a robot holding the role is served from the cache"
    authorizer.close()


def test_a_record_fetched_again_for_a_role_is_checked_whole() -> None:
    """A robot deactivated meanwhile is refused as inactive, not let through for its role."""
    authorizer = LedgerOfOneRobot(robot_record())
    authorize(authorizer)
    authorizer.record = robot_record(roles=("reviewer",), active=False)
    authorizer.now += 3
    with pytest.raises(Forbidden) as refused:
        authorize(authorizer, "reviewer")
    assert refused.value.code == "robot_inactive"
    authorizer.close()
