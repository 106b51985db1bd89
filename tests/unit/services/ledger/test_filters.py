"""Filters: bounded in number and lifetime, cursors that move only once answered, criteria
validated and resolved as nodes do."""

from __future__ import annotations

import pytest

from services.ledger.filters import (
    MAX_BLOCK_HASHES,
    FilterNotFound,
    Filters,
    LogCriteria,
    TooManyFilters,
)
from services.ledger.refusals import InvalidParams
from tests.clock import Clock


def test_a_filter_nobody_polls_expires_and_polling_keeps_it() -> None:
    clock = Clock(100.0)
    filters = Filters(max_filters=10, timeout_s=60, clock=clock)
    kept, dropped = filters.install(None, 5), filters.install(None, 5)
    clock.now += 50
    filters.changes(kept, 6)
    clock.now += 50
    assert filters.changes(kept, 7).first == 6
    with pytest.raises(FilterNotFound):
        filters.changes(dropped, 7)
    assert len(filters) == 1


def test_the_number_of_filters_is_bounded_and_expired_ones_make_room() -> None:
    clock = Clock(100.0)
    filters = Filters(max_filters=2, timeout_s=60, clock=clock)
    filters.install(None, 0)
    filters.install(LogCriteria(), 0)
    with pytest.raises(TooManyFilters):
        filters.install(None, 0)
    clock.now += 61
    assert filters.install(None, 0).startswith("0x")


def test_one_client_holds_its_share_of_the_filters_and_the_rest_is_for_others() -> None:
    clock = Clock(100.0)
    filters = Filters(max_filters=4, timeout_s=60, clock=clock, max_per_client=2)
    greedy = [filters.install(None, 0, "192.0.2.1"), filters.install(LogCriteria(), 0, "192.0.2.1")]
    with pytest.raises(TooManyFilters, match="too many filters from one client: at most 2"):
        filters.install(None, 0, "192.0.2.1")
    filters.install(None, 0, "192.0.2.2")
    filters.install(None, 0, None)  # the node's own count against the total only
    assert filters.uninstall(greedy[0])
    filters.install(None, 0, "192.0.2.1")
    with pytest.raises(TooManyFilters, match="too many filters: at most 4"):
        filters.install(None, 0, "192.0.2.3")
    clock.now += 61
    assert len(filters) == 0


def test_the_cursor_moves_only_when_the_answer_was_given() -> None:
    filters = Filters(max_filters=2, timeout_s=60)
    filter_id = filters.install(LogCriteria(), 10)
    first = filters.changes(filter_id, 15)
    assert (first.first, first.last) == (11, 15)
    assert filters.changes(filter_id, 15).first == 11  # not answered: asked again
    filters.reported(filter_id, 15)
    assert filters.changes(filter_id, 16).first == 16


def test_block_filters_answer_a_bounded_number_of_hashes_per_poll() -> None:
    filters = Filters(max_filters=2, timeout_s=60)
    filter_id = filters.install(None, 0)
    changes = filters.changes(filter_id, 3 * MAX_BLOCK_HASHES)
    assert changes.last - changes.first + 1 == MAX_BLOCK_HASHES


def test_ids_are_unguessable_and_uninstall_is_once() -> None:
    filters = Filters(max_filters=5, timeout_s=60)
    ids = {filters.install(None, 0) for _ in range(5)}
    assert len(ids) == 5
    assert all(len(filter_id) == 34 for filter_id in ids)
    one = ids.pop()
    assert filters.uninstall(one) is True
    assert filters.uninstall(one) is False
    with pytest.raises(FilterNotFound):
        filters.criteria(one)


def test_criteria_are_bounded_and_resolved_as_nodes_do() -> None:
    with pytest.raises(InvalidParams, match="exceeded maximum topics len"):
        LogCriteria(topics=(None,) * 5)
    with pytest.raises(InvalidParams, match="too many addresses"):
        LogCriteria(addresses=tuple(bytes(20) for _ in range(1001)))
    with pytest.raises(InvalidParams, match="block height is 7 but requested was 9"):
        LogCriteria(from_block=9).resolve(7)
    resolved = LogCriteria(from_block="earliest", to_block=100).resolve(7)
    assert (resolved.from_block, resolved.to_block) == (0, 7)
    window = LogCriteria(from_block=3, to_block=5).window(1, 10)
    assert window is not None
    assert (window.from_block, window.to_block) == (3, 5)
    assert LogCriteria(to_block=5).window(6, 10) is None
    latest = LogCriteria().window(6, 10)
    assert latest is not None
    assert (latest.from_block, latest.to_block) == (6, 10)
