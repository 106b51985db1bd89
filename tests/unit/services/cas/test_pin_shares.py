"""Each robot's share of pinned bytes: what a pin is charged, on every path that pins, and
that a pin past the share is refused with nothing stored and nothing pinned.

Without a share one registered robot could fill the disk that every robot's data lives on.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from robocloud.cid import CID, DAG_PB, RAW, Block
from robocloud.unixfs import ImportParams
from services.cas.pins import PinQuotaExceeded, PinSet
from services.cas.shares import Share
from services.cas.store import ContentStore
from services.cas.uploads import BlockCollector, FileAdder
from tests.unit.services.cas.test_car_import import counting_walk_reads, imported, node_over
from tests.unit.services.cas.test_pins import ALICE, BOB, ONE, TWO
from tests.unit.services.cas.test_reachability import file_node, put, raw


def test_a_pin_past_the_share_is_refused_and_a_removal_gives_its_charge_back(
    tmp_path: Path,
) -> None:
    pins = PinSet(tmp_path / "pins.log")
    pins.add_all({ONE: 60}, ALICE, max_bytes=100)
    with pytest.raises(PinQuotaExceeded) as refused:
        pins.add_all({TWO: 41}, ALICE, max_bytes=100)
    assert (refused.value.owner, refused.value.size, refused.value.used) == (ALICE, 41, 60)
    assert refused.value.limit == 100
    assert pins.snapshot() == {ONE: frozenset({ALICE})}
    assert pins.add_all({TWO: 40}, BOB, max_bytes=100) == [TWO]
    assert pins.add_all({ONE: 60}, ALICE, max_bytes=60) == []
    pins.remove([ONE], ALICE)
    assert pins.pinned_bytes(ALICE) == 0
    assert pins.add_all({TWO: 41}, ALICE, max_bytes=100) == [TWO]
    assert (pins.pinned_bytes(ALICE), pins.pinned_bytes(BOB)) == (41, 40)
    pins.close()


def test_charges_survive_a_restart_and_a_compaction(tmp_path: Path) -> None:
    path = tmp_path / "pins.log"
    pins = PinSet(path)
    pins.add_all({ONE: 7, TWO: 11}, ALICE)
    for _ in range(1_000):
        pins.add_all({TWO: 5}, BOB)
        pins.remove([TWO], BOB)
    pins.close()
    reopened = PinSet(path)
    assert len(path.read_text().splitlines()) == 1
    assert (reopened.pinned_bytes(ALICE), reopened.pinned_bytes(BOB)) == (18, 0)
    with pytest.raises(PinQuotaExceeded):
        reopened.add_all({CID.from_block(b"x"): 3}, ALICE, max_bytes=20)
    reopened.close()


def test_pins_of_a_journal_without_charges_are_charged_their_stored_dag_once(
    tmp_path: Path,
) -> None:
    leaf = raw(b"pinned before pins were charged")
    node = file_node(leaf)
    root = CID.from_block(node, DAG_PB)
    store = ContentStore.open(tmp_path, [])
    put(store, leaf, Block(root, node))
    store.close()
    (tmp_path / "pins.log").write_text(
        json.dumps({"op": "add", "cids": [str(root)], "owner": ALICE}) + "\n"
    )
    reopened = ContentStore.open(tmp_path, [])
    assert reopened.pins.pinned_bytes(ALICE) == len(node) + len(leaf.data)
    reopened.close()
    (line,) = (tmp_path / "pins.log").read_text().splitlines()
    assert json.loads(line)["bytes"] == [len(node) + len(leaf.data)]


def test_each_root_is_charged_its_whole_dag_even_when_a_request_shares_blocks(
    store: ContentStore,
) -> None:
    """Two roots over one leaf, pinned together: the shared walk reads the leaf once, and
    each root is still charged it. Charged to the first alone, unpinning the first left the
    second pinned and the leaf kept for nothing."""
    leaf = raw(b"s" * 1000)
    first, second = node_over([leaf.cid], b"first"), node_over([leaf.cid], b"second")
    put(store, leaf, first, second)
    store.pin([first.cid, second.cid], ALICE, share=Share(10_000))
    assert store.pins.pinned_bytes(ALICE) == 2 * len(leaf.data) + len(first.data) + len(second.data)
    store.unpin([first.cid], ALICE)
    assert store.pins.pinned_bytes(ALICE) == len(leaf.data) + len(second.data)


def test_a_part_of_a_dag_pinned_beside_it_is_charged_on_its_own(store: ContentStore) -> None:
    """Pin a DAG, then the DAG again with a part of it, then unpin the DAG: the part stays
    charged. Walked after the DAG the robot already pinned, the part was read as seen."""
    leaf = raw(b"p" * 3000)
    whole = node_over([leaf.cid], b"whole")
    put(store, leaf, whole)
    store.pin([whole.cid], ALICE)
    store.pin([whole.cid, leaf.cid], ALICE, share=Share(10_000))
    store.unpin([whole.cid], ALICE)
    assert store.pins.pinned_bytes(ALICE) == len(leaf.data)


def test_a_sub_dag_linked_twice_counts_twice_as_in_kubos_cumulative_size(
    store: ContentStore,
) -> None:
    leaf = raw(b"twice" * 100)
    node = node_over([leaf.cid, leaf.cid], b"node")
    put(store, leaf, node)
    store.pin([node.cid], ALICE)
    assert store.pins.pinned_bytes(ALICE) == len(node.data) + 2 * len(leaf.data)


def test_pin_add_past_the_share_pins_nothing(store: ContentStore) -> None:
    small, large = raw(b"small"), raw(b"L" * 500)
    put(store, small, large)
    with pytest.raises(PinQuotaExceeded) as refused:
        store.pin([small.cid, large.cid], ALICE, share=Share(100))
    assert refused.value.size == len(small.data) + len(large.data)
    assert store.pinned() == {}
    store.pin([small.cid], ALICE, share=Share(100))
    assert store.pinned() == {small.cid: frozenset({ALICE})}


def test_block_put_past_the_share_stores_nothing(store: ContentStore) -> None:
    collector = BlockCollector(store, RAW, pin=True)
    for data in (b"a" * 60, b"b" * 60):
        collector.begin("block")
        collector.write(data)
        collector.end()
    with pytest.raises(PinQuotaExceeded):
        collector.commit(ALICE, Share(100))
    assert store.usage()[0] == 0
    assert store.pinned() == {}
    unpinned = BlockCollector(store, RAW, pin=False)
    unpinned.blocks = collector.blocks
    assert len(unpinned.commit(ALICE, Share(100))) == 2


def test_an_add_is_charged_the_size_it_answers_and_past_the_share_stores_nothing(
    store: ContentStore,
) -> None:
    def add(data: bytes, max_bytes: int) -> int:
        adder = FileAdder(store, ImportParams(), only_hash=False, pin=True)
        try:
            adder.begin("file")
            adder.write(data)
            adder.end()
            (added,) = adder.commit(ALICE, Share(max_bytes))
            return added.dag_size
        finally:
            adder.discard()

    size = add(b"f" * 300_000, 400_000)
    assert store.pins.pinned_bytes(ALICE) == size > 300_000
    blocks = store.usage()[0]
    with pytest.raises(PinQuotaExceeded):
        add(b"g" * 200_000, 400_000)
    assert store.usage()[0] == blocks
    assert store.pins.pinned_bytes(ALICE) == size


def test_a_car_whose_first_root_is_incomplete_has_the_shared_dag_charged_to_the_second(
    store: ContentStore,
) -> None:
    """The first root's walk reads the shared DAG and then misses a block: the second root,
    that DAG itself, was skipped as seen and would have been pinned for nothing."""
    shared = node_over([raw(b"x" * 5000).cid], b"shared")
    absent = raw(b"never sent")
    first = node_over([shared.cid, absent.cid], b"first")
    blocks = [first, shared, raw(b"x" * 5000)]
    roots = imported(store, [first.cid, shared.cid], blocks, Share(100_000))
    assert [bool(root.pin_error) for root in roots] == [True, False]
    assert store.pins.pinned_bytes(ALICE) == len(shared.data) + 5000


def test_a_dag_that_doubles_at_every_level_is_sized_in_linear_time_and_refused(
    store: ContentStore,
) -> None:
    """300 levels, each linking the one below twice: 300 blocks, a cumulative size past
    2**300. Walked once and summed once per block, then refused like any pin too large."""
    below = raw(b"bottom")
    blocks = [below]
    for level in range(300):
        below = node_over([below.cid, below.cid], str(level).encode())
        blocks.append(below)
    put(store, *blocks)
    with pytest.raises(PinQuotaExceeded) as refused:
        store.pin([below.cid], ALICE, share=Share(16 * 1024**3))
    assert refused.value.size > 2**300
    assert store.pinned() == {}


def test_a_pin_too_large_stops_reading_once_it_passes_the_room_left(
    store: ContentStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With peers, every block a pin reads may be fetched and stored: a DAG of any size was
    read whole before its size was known to be too large for the robot's share."""
    leaves = [raw(bytes([n]) * 1000) for n in range(10)]
    root = node_over([leaf.cid for leaf in leaves], b"ten leaves")
    put(store, root, *leaves)
    store.pin([leaves[0].cid], ALICE)
    reads = []
    get = store.blocks.get

    def counted(cid: CID) -> bytes:
        reads.append(cid)
        return get(cid)

    monkeypatch.setattr(store.blocks, "get", counted)
    with pytest.raises(PinQuotaExceeded) as refused:
        store.pin([leaves[0].cid, root.cid], ALICE, share=Share(3500))
    assert len(reads) <= 4
    assert (refused.value.used, refused.value.limit) == (1000, 3500)
    assert refused.value.size > 2500
    assert store.pinned() == {leaves[0].cid: frozenset({ALICE})}


def test_an_import_stops_reading_a_stored_dag_once_it_passes_the_room_left(
    store: ContentStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A CAR of one small node linking to a large DAG another robot stored: the import read
    all of it before the pin was found too large for the robot's share."""
    leaves = [raw(bytes([n]) * 1000) for n in range(10)]
    stored = node_over([leaf.cid for leaf in leaves], b"ten leaves")
    put(store, stored, *leaves)
    near = node_over([stored.cid], b"near")
    reads = counting_walk_reads(store, monkeypatch)
    with pytest.raises(PinQuotaExceeded) as refused:
        imported(store, [near.cid], [near], Share(3500))
    assert sum(reads.values()) <= 5
    assert (refused.value.used, refused.value.limit) == (0, 3500)
    assert refused.value.size > 3500
    assert store.usage()[0] == 11
    assert store.pinned() == {}


def test_importing_a_dag_the_robot_pins_again_neither_walks_nor_charges_it(
    store: ContentStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A robot sending its CAR again (a retry) with its share nearly used: the DAG it pins
    needs no walk, and its bytes must not count against the room left."""
    leaves = [raw(bytes([n]) * 1000) for n in range(8)]
    root = node_over([leaf.cid for leaf in leaves], b"eight leaves")
    assert imported(store, [root.cid], [root, *leaves], Share(9000))[0].pin_error == ""
    used = store.pins.pinned_bytes(ALICE)
    reads = counting_walk_reads(store, monkeypatch)
    again = imported(store, [root.cid], [root, *leaves], Share(9000))
    assert [(answer.cid, answer.pin_error) for answer in again] == [(root.cid, "")]
    assert not reads
    assert store.pins.pinned_bytes(ALICE) == used
