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
    assert pins.add_all({ONE: 3}, ALICE) == [ONE]
    assert pins.add_all({ONE: 3}, ALICE) == []
    assert pins.add_all({ONE: 3}, BOB) == [ONE]
    assert pins.owners(ONE) == {ALICE, BOB}
    pins.remove([ONE], ALICE)
    assert pins.snapshot() == {ONE: frozenset({BOB})}


def test_removing_another_robots_pin_is_refused(tmp_path: Path) -> None:
    pins = PinSet(tmp_path / "pins.log")
    pins.add_all({ONE: 3}, ALICE)
    with pytest.raises(PinNotOwned) as raised:
        pins.remove([ONE], BOB)
    assert (raised.value.cid, raised.value.owner) == (ONE, BOB)
    assert pins.owners(ONE) == {ALICE}


def test_removal_is_all_or_nothing(tmp_path: Path) -> None:
    pins = PinSet(tmp_path / "pins.log")
    pins.add_all({ONE: 3}, ALICE)
    with pytest.raises(NotPinned) as raised:
        pins.remove([ONE, TWO], ALICE)
    assert raised.value.cid == TWO
    assert pins.owners(ONE) == {ALICE}


def test_the_journal_is_replayed_on_open(tmp_path: Path) -> None:
    """Two dead lines are too few to compact (``test_pins_journal``)."""
    path = tmp_path / "pins.log"
    pins = PinSet(path)
    pins.add_all({ONE: 3}, ALICE)
    pins.add_all({TWO: 3}, ALICE)
    pins.add_all({TWO: 3}, BOB)
    pins.remove([TWO], ALICE)
    pins.close()
    assert len(path.read_text().splitlines()) == 4
    reopened = PinSet(path)
    assert reopened.snapshot() == {ONE: frozenset({ALICE}), TWO: frozenset({BOB})}
    assert len(path.read_text().splitlines()) == 4
    reopened.close()


def test_a_many_root_pin_torn_by_a_crash_leaves_none_of_its_roots(tmp_path: Path) -> None:
    """One journal line a request: a crash mid-write tears that line, which is dropped on
    read. With a line a root, the first roots of a pin/add stayed pinned after the crash."""
    path = tmp_path / "pins.log"
    pins = PinSet(path)
    pins.add_all({ONE: 3}, BOB)
    roots = [CID.from_block(bytes([n])) for n in range(50)]
    assert pins.add_all(dict.fromkeys(roots, 1), ALICE) == roots
    pins.close()
    journal = path.read_bytes()
    assert journal.count(b"\n") == 2
    path.write_bytes(journal[: len(journal) - len(journal.splitlines()[-1]) // 2])
    reopened = PinSet(path)
    assert reopened.snapshot() == {ONE: frozenset({BOB})}
    reopened.close()


def test_a_journal_written_one_root_a_line_is_still_read(tmp_path: Path) -> None:
    path = tmp_path / "pins.log"
    path.write_text(
        f'{{"op":"add","cid":"{ONE}","owner":"{ALICE}"}}\n'
        f'{{"op":"add","cid":"{TWO}","owner":"{ALICE}"}}\n'
        f'{{"op":"rm","cid":"{ONE}","owner":"{ALICE}"}}\n'
    )
    pins = PinSet(path)
    assert pins.snapshot() == {TWO: frozenset({ALICE})}
    pins.close()
