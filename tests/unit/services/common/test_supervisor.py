"""`make up`'s supervisor: how long it waits before starting a dead service again."""

from __future__ import annotations

from services.common.supervisor import restart_delay


def test_the_delay_doubles_with_each_death_in_a_row_up_to_30_s() -> None:
    assert [restart_delay(deaths) for deaths in range(1, 9)] == [1, 2, 4, 8, 16, 30, 30, 30]
