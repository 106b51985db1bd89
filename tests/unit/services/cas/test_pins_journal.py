"""The pin journal at start: compacted only when it holds many dead lines, and a start that
cannot compact it (a full disk) starts all the same.

Every start rewrote the journal, so once a pin existed a cas whose disk had filled could not
start again, not even so that an operator could collect garbage.
"""

from __future__ import annotations

import errno
import logging
from collections.abc import Callable
from pathlib import Path

import pytest

import services.common.durable
from robocloud.cid import CID
from services.cas.pins import PinSet
from tests.unit.services.cas.test_pins import ALICE, BOB, ONE, TWO


@pytest.fixture
def full_disk(monkeypatch: pytest.MonkeyPatch) -> Callable[[], None]:
    """Call it and no new file can be written (appends to open ones still can)."""

    def fill() -> None:
        def no_space(path: Path, data: bytes, *, mode: int = 0o644) -> None:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))

        monkeypatch.setattr(services.common.durable, "write_synced", no_space)

    return fill


def journal(path: Path, churn: int) -> None:
    """Alice keeps ``ONE`` and Bob ``TWO``; Alice also pins and unpins ``TWO`` ``churn``
    times, leaving ``2 * churn`` dead lines."""
    pins = PinSet(path)
    pins.add_all({ONE: 3}, ALICE)
    pins.add_all({TWO: 3}, BOB)
    for _ in range(churn):
        pins.add_all({TWO: 3}, ALICE)
        pins.remove([TWO], ALICE)
    pins.close()


def reopened(path: Path) -> dict[CID, frozenset[str]]:
    pins = PinSet(path)
    try:
        return pins.snapshot()
    finally:
        pins.close()


EXPECTED = {ONE: frozenset({ALICE}), TWO: frozenset({BOB})}
CHURN = 1_000
"""2,000 dead lines: past ``durable.MIN_DEAD_LINES``, so a start compacts them."""


def test_a_start_leaves_a_journal_with_few_dead_lines_as_it_is(
    tmp_path: Path, full_disk: Callable[[], None]
) -> None:
    path = tmp_path / "pins.log"
    journal(path, churn=3)
    before = path.read_bytes(), path.stat().st_ino
    full_disk()
    pins = PinSet(path)
    assert pins.snapshot() == EXPECTED
    assert (path.read_bytes(), path.stat().st_ino) == before
    pins.close()


def test_a_journal_with_many_dead_lines_is_compacted_at_start(tmp_path: Path) -> None:
    path = tmp_path / "pins.log"
    journal(path, churn=CHURN)
    assert len(path.read_text().splitlines()) == 2 + 2 * CHURN
    pins = PinSet(path)
    assert pins.snapshot() == EXPECTED
    pins.add_all({ONE: 3}, BOB)
    pins.close()
    assert len(path.read_text().splitlines()) == 2 + 1
    assert reopened(path) == {ONE: frozenset({ALICE, BOB}), TWO: frozenset({BOB})}


def test_a_compaction_that_fails_is_logged_and_the_journal_kept(
    tmp_path: Path, full_disk: Callable[[], None], caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "pins.log"
    journal(path, churn=CHURN)
    before = path.read_bytes()
    full_disk()
    with caplog.at_level(logging.WARNING, "robocloud.durable"):
        pins = PinSet(path)
    assert "journal not compacted" in caplog.text
    assert pins.snapshot() == EXPECTED
    assert path.read_bytes() == before
    assert list(tmp_path.iterdir()) == [path]
    pins.add_all({ONE: 3}, BOB)
    pins.close()
    assert path.read_bytes().startswith(before)
    assert reopened(path) == {ONE: frozenset({ALICE, BOB}), TWO: frozenset({BOB})}
