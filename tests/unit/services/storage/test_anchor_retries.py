"""How the anchorer paces its retries: back off from a failing peer, not from a missing role."""

from __future__ import annotations

import pytest

from services.storage.anchoring import MAX_RETRY_S, NotYetAnchoring, retry_wait


def test_a_failing_peer_is_asked_half_as_often_each_time_down_to_the_cap() -> None:
    down = ConnectionError("ledger unreachable")
    waits = [retry_wait(1.0, failures, down) for failures in range(8)]
    assert waits == [1.0, 2.0, 4.0, 8.0, 16.0, MAX_RETRY_S, MAX_RETRY_S, MAX_RETRY_S]


@pytest.mark.parametrize("failures", [0, 3, 40])
def test_a_node_waiting_for_its_role_asks_again_at_the_base_interval(failures: int) -> None:
    waiting = NotYetAnchoring("the node is registered and lacks the storage_node role")
    assert retry_wait(0.2, failures, waiting) == 0.2
