"""Owned pins: each robot removes only its own, all or nothing, and the journal survives."""

from __future__ import annotations

from pathlib import Path

import pytest

from robocloud.cid import CID
from services.cas.pins import NotPinned, PinNotOwned, PinSet

ALICE = "0x" + "a1" * 20
BOB = "0x" + "b0" * 20
ONE, TWO = CID.from_block(b"one"), CID.from_block(b"two")


def test_two_robots_pin_the_same_cid_and_each_owns_its_pin(tmp_path: Path) -> None:
    pins = PinSet(tmp_path / "pins.log")
    assert pins.add(ONE, ALICE)
    assert not pins.add(ONE, ALICE)
    assert pins.add(ONE, BOB)
    assert pins.owners(ONE) == {ALICE, BOB}
    pins.remove([ONE], ALICE)
    assert pins.snapshot() == {ONE: frozenset({BOB})}


def test_removing_another_robots_pin_is_refused(tmp_path: Path) -> None:
    pins = PinSet(tmp_path / "pins.log")
    pins.add(ONE, ALICE)
    with pytest.raises(PinNotOwned) as raised:
        pins.remove([ONE], BOB)
    assert (raised.value.cid, raised.value.owner) == (ONE, BOB)
    assert pins.owners(ONE) == {ALICE}


def test_removal_is_all_or_nothing(tmp_path: Path) -> None:
    pins = PinSet(tmp_path / "pins.log")
    pins.add(ONE, ALICE)
    with pytest.raises(NotPinned) as raised:
        pins.remove([ONE, TWO], ALICE)
    assert raised.value.cid == TWO
    assert pins.owners(ONE) == {ALICE}


def test_the_journal_is_replayed_and_compacted_on_open(tmp_path: Path) -> None:
    path = tmp_path / "pins.log"
    pins = PinSet(path)
    pins.add(ONE, ALICE)
    pins.add(TWO, ALICE)
    pins.add(TWO, BOB)
    pins.remove([TWO], ALICE)
    pins.close()
    assert len(path.read_text().splitlines()) == 4
    reopened = PinSet(path)
    assert reopened.snapshot() == {ONE: frozenset({ALICE}), TWO: frozenset({BOB})}
    assert len(path.read_text().splitlines()) == 2
    reopened.close()
