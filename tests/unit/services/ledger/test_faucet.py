"""The faucet's limits: per address (kept across restarts) and a global minute budget."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from services.ledger.faucet import FaucetLimits, RateLimited

Opener = Callable[..., FaucetLimits]


class Clock:
    def __init__(self) -> None:
        self.now = 1_000_000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def opened(tmp_path: Path, clock: Clock) -> Opener:
    """Open the limits stored in one file, as a restarted ledger would (one grant an hour)."""

    def open_limits(per_minute: int = 60) -> FaucetLimits:
        return FaucetLimits(tmp_path / "faucet.sqlite", 3600, per_minute, clock)

    return open_limits


def test_once_per_address_per_interval(clock: Clock, opened: Opener) -> None:
    limits = opened()
    limits.acquire("0xA")
    clock.now += 600
    with pytest.raises(RateLimited) as refused:
        limits.acquire("0xA")
    assert refused.value.retry_after_s == pytest.approx(3000)
    limits.acquire("0xB")
    clock.now += 3000
    limits.acquire("0xA")


def test_grants_survive_a_reopen_and_expired_ones_are_dropped(clock: Clock, opened: Opener) -> None:
    limits = opened()
    limits.acquire("0xA")
    clock.now += 3000
    limits.acquire("0xB")
    limits.close()
    clock.now += 1000
    reopened = opened()
    reopened.acquire("0xA")
    with pytest.raises(RateLimited, match="0xB was funded 1000 s ago"):
        reopened.acquire("0xB")


def test_a_released_grant_may_retry_at_once_even_after_a_reopen(opened: Opener) -> None:
    limits = opened()
    limits.acquire("0xA")
    limits.release("0xA")
    limits.close()
    opened().acquire("0xA")


def test_a_release_gives_back_its_own_place_in_the_minutes_budget(
    clock: Clock, opened: Opener
) -> None:
    """It gave back the newest grant's place and kept the failed one's: once that expired,
    three grants fit in 31 s under a budget of two a minute."""
    limits = opened(per_minute=2)
    limits.acquire("0xA")
    clock.now += 30
    limits.acquire("0xB")
    limits.release("0xA")
    clock.now += 31
    limits.acquire("0xC")
    with pytest.raises(RateLimited, match="budget for this minute"):
        limits.acquire("0xD")


def test_global_budget_per_minute(clock: Clock, opened: Opener) -> None:
    limits = opened(per_minute=2)
    limits.acquire("0xA")
    clock.now += 10
    limits.acquire("0xB")
    with pytest.raises(RateLimited, match="budget for this minute") as refused:
        limits.acquire("0xC")
    assert refused.value.retry_after_s == pytest.approx(50)
    clock.now += 50
    limits.acquire("0xC")
