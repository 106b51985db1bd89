"""The faucet's limits: per address (kept across restarts) and a global minute budget."""

from __future__ import annotations

import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest

from services.ledger.faucet import FaucetLimits, RateLimited
from tests.clock import Clock
from tests.unit.services.ledger.crash import FailingDiskChild, copy_as_killed, failing_fsync_library

Opener = Callable[..., FaucetLimits]


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


FAILING_DISK = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from services.ledger.faucet import FaucetLimits, RateLimited
    limits = FaucetLimits(Path(sys.argv[1]), 3600, 60)
    print("ready", flush=True)
    for line in sys.stdin:
        action, address = line.split()
        try:
            getattr(limits, action)(address)
        except RateLimited:
            print("refused", flush=True)
        except Exception as exc:
            print("failed", type(exc).__name__, flush=True)
        else:
            print("done", flush=True)
    """
)


@pytest.mark.parametrize("persistent", [False, True], ids=["one-failure", "failing-until-answered"])
def test_a_grant_or_release_whose_fsync_failed_is_answered_as_a_restart_finds_it(
    tmp_path: Path, persistent: bool
) -> None:
    """A write whose commit's fsync of the write-ahead log failed raised, yet its frames,
    commit marker included, stayed in the log and a restart before the next write recovered
    it: a grant whose acquire raised (its robot never funded) refused the robot for the whole
    interval, and a release that raised (the grant kept) was undone. The files as a kill -9
    right after each answer leaves them must hold what was answered, whether the disk failed
    once or until then."""
    library = failing_fsync_library(tmp_path)
    trigger, path = tmp_path / "fail", tmp_path / "faucet.sqlite"
    child = FailingDiskChild(FAILING_DISK, path, library, trigger, persistent)
    try:
        assert child.ask("acquire 0xA") == "done"
        assert child.ask("acquire 0xB") == "done"
        trigger.touch()
        failed_grant = child.ask("acquire 0xC")
        assert trigger.exists() == persistent  # the fault happened
        trigger.unlink(missing_ok=True)
        after_grant = copy_as_killed(path, tmp_path / "after-grant")
        assert failed_grant == "failed OperationalError"
        trigger.touch()
        failed_release = child.ask("release 0xB")
        assert trigger.exists() == persistent
        trigger.unlink(missing_ok=True)
        after_release = copy_as_killed(path, tmp_path / "after-release")
        assert failed_release == "failed OperationalError"
        assert child.ask("acquire 0xB") == "refused"  # the release failed: the grant stays
        assert child.ask("acquire 0xC") == "done"  # its robot asks again
    finally:
        child.kill()
    for crashed in (after_grant, after_release):
        limits = FaucetLimits(crashed, 3600, 60)
        limits.acquire("0xC")
        for granted in ("0xA", "0xB"):
            with pytest.raises(RateLimited):
                limits.acquire(granted)
        limits.close()
    limits = FaucetLimits(path, 3600, 60)
    for granted in ("0xA", "0xB", "0xC"):
        with pytest.raises(RateLimited):
            limits.acquire(granted)
    limits.close()
