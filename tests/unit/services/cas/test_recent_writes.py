"""The new bytes a robot may write in a rolling hour: the window slides a minute at a time,
a refusal says when to try again, and a write that failed is not counted."""

from __future__ import annotations

import pytest

from services.cas.shares import BUCKET_S, WINDOW_S, RecentWrites, WriteRateExceeded
from tests.clock import Clock
from tests.unit.services.cas.test_pins import ALICE, BOB


def test_writes_past_the_hourly_bound_are_refused_until_the_oldest_leave_the_window() -> None:
    clock = Clock()
    writes = RecentWrites(clock)
    with writes.charge(ALICE, 600, 1000):
        pass
    clock.now += 10 * BUCKET_S
    with writes.charge(ALICE, 300, 1000):
        pass
    with pytest.raises(WriteRateExceeded) as refused, writes.charge(ALICE, 200, 1000):
        pytest.fail("a refused write must not run")
    assert (refused.value.written, refused.value.size, refused.value.limit) == (900, 200, 1000)
    assert WINDOW_S - 10 * BUCKET_S < refused.value.retry_after_s <= WINDOW_S - 9 * BUCKET_S
    with writes.charge(BOB, 1000, 1000):
        pass
    clock.now += refused.value.retry_after_s
    assert writes.written(ALICE) == 300
    with writes.charge(ALICE, 200, 1000):
        pass
    assert writes.written(ALICE) == 500


def test_a_write_larger_than_the_bound_waits_the_whole_window_and_none_is_unbounded() -> None:
    writes = RecentWrites(Clock())
    with pytest.raises(WriteRateExceeded) as refused, writes.charge(ALICE, 2000, 1000):
        pass
    assert refused.value.retry_after_s == WINDOW_S
    with writes.charge(ALICE, 10**12, None):
        pass
    assert writes.written(ALICE) == 10**12


def test_a_write_that_fails_is_given_back() -> None:
    writes = RecentWrites(Clock())
    with writes.charge(ALICE, 100, 1000):
        pass
    with pytest.raises(OSError, match="disk full"), writes.charge(ALICE, 700, 1000):
        raise OSError("disk full")
    assert writes.written(ALICE) == 100


def test_robots_are_forgotten_once_their_writes_leave_the_window() -> None:
    """One-off keys must not be kept for good: every write sweeps, at most once a minute."""
    clock = Clock()
    writes = RecentWrites(clock)
    for number in range(1000):
        with writes.charge(f"0x{number:040x}", 1, 10):
            pass
    assert writes.robots() == 1000
    clock.now += WINDOW_S + 2 * BUCKET_S
    assert writes.robots() == 1000
    with writes.charge(ALICE, 1, 10):
        pass
    assert writes.robots() == 1


def test_bytes_added_for_good_count_and_a_refused_addition_counts_nothing() -> None:
    """A block fetched from a peer for a pin is stored as it comes: counted with no block
    to give it back from, and, refused, not counted."""
    writes = RecentWrites(Clock())
    writes.add(ALICE, 700, 1000)
    with pytest.raises(WriteRateExceeded) as refused:
        writes.add(ALICE, 400, 1000)
    assert (refused.value.written, refused.value.size) == (700, 400)
    assert writes.written(ALICE) == 700
    writes.add(ALICE, 300, 1000)
    assert writes.written(ALICE) == 1000
