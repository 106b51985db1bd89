"""``dag/import`` of a CAR naming many roots: one walk through what they share, one pin
journal line, and a root over a missing block reported as such whatever came before it."""

from __future__ import annotations

import itertools
import os
import threading
from collections import Counter
from pathlib import Path

import pytest

from robocloud.car import write_car
from robocloud.cid import CID, DAG_PB, RAW, Block
from robocloud.dagpb import Link, PBNode
from robocloud.unixfs import ImportParams, import_bytes
from services.cas.shares import UNBOUNDED, Share
from services.cas.store import CarRejected, ContentStore, ImportedRoot
from services.cas.uploads import BATCH_BYTES, PIPE_BYTES, CarImport
from tests.unit.robocloud.test_car import carv2
from tests.unit.services.cas.test_reachability import ALICE


def imported(
    store: ContentStore,
    roots: list[CID],
    blocks: list[Block],
    share: Share = UNBOUNDED,
    *,
    pin_roots: bool = True,
) -> list[ImportedRoot]:
    """``dag/import`` of one CAR for ALICE, as the route runs it."""
    car_import = CarImport(store, pin_roots=pin_roots)
    try:
        car_import.begin("import.car")
        for part in write_car(roots, blocks):
            car_import.write(part)
        car_import.end()
        return car_import.commit(ALICE, share)
    finally:
        car_import.discard()


def counting_walk_reads(store: ContentStore, monkeypatch: pytest.MonkeyPatch) -> Counter[CID]:
    """The blocks a walk reads from now on, staged or stored, with the times each is read."""
    reads: Counter[CID] = Counter()
    staged_or_stored = store._staged_or_stored

    def counted(cid: CID, **where: object) -> bytes:
        reads[cid] += 1
        return staged_or_stored(cid, **where)  # type: ignore[arg-type]

    monkeypatch.setattr(store, "_staged_or_stored", counted)
    return reads


def node_over(children: list[CID], label: bytes) -> Block:
    data = PBNode([Link(child, "", 1) for child in children], label).encode()
    return Block(CID.from_block(data, DAG_PB, 1), data)


def test_a_dag_named_under_many_roots_is_walked_once_and_pinned_in_one_line(
    store: ContentStore, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each root used to be walked on its own and pinned with its own journal line (and
    fsync): a header's 1,000 roots over one 41-block file read about 41,000 blocks, and
    CAR parts are not limited in number."""
    blocks, file_root = import_bytes(os.urandom(40_000), ImportParams(chunk_size=1000))
    shared = [node_over([file_root], str(n).encode()) for n in range(500)]
    roots = [file_root] * 500 + [block.cid for block in shared]
    reads = counting_walk_reads(store, monkeypatch)
    journal = tmp_path / "pins.log"
    before = journal.read_bytes().count(b"\n") if journal.exists() else 0
    answers = imported(store, roots, [*blocks, *shared])
    assert answers == [ImportedRoot(root, "") for root in dict.fromkeys(roots)]  # each once
    assert set(reads.values()) == {1}
    assert len(reads) == len(blocks) + len(shared)
    assert journal.read_bytes().count(b"\n") == before + 1
    assert set(store.pins.snapshot()) == set(roots)


def test_a_root_over_a_block_another_root_stopped_at_is_not_pinned(
    store: ContentStore,
) -> None:
    gone = CID.from_block(b"gone", RAW, 1)
    middle = node_over([gone], b"middle")
    first, second = node_over([middle.cid], b"first"), node_over([middle.cid], b"second")
    whole = node_over([], b"whole")
    roots = [first.cid, second.cid, whole.cid]
    answers = imported(store, roots, [middle, first, second, whole])
    assert [answer.pin_error for answer in answers] == [
        f"block {gone} of the DAG is missing; {first.cid} was not pinned",
        f"block {gone} of the DAG is missing; {second.cid} was not pinned",
        "",
    ]
    assert set(store.pins.snapshot()) == {whole.cid}


def test_without_pin_roots_no_root_is_walked_or_answered(
    store: ContentStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    """kubo answers no root when it pins none. Walking them read a DAG of any size stored
    under a root the CAR names (or fetched it from the peers) for a pin nobody asked for."""
    stored = [node_over([], str(n).encode()) for n in range(100)]
    for block in stored:
        store.put_blocks([block.data], DAG_PB, ALICE, pin=False)
    over_them = node_over([block.cid for block in stored], b"over them")
    reads = counting_walk_reads(store, monkeypatch)
    assert imported(store, [over_them.cid], [over_them], pin_roots=False) == []
    assert not reads
    assert store.usage()[0] == 101
    assert store.pinned() == {}


def reading_threads() -> list[threading.Thread]:
    return [thread for thread in threading.enumerate() if thread.name == "dag-import"]


def test_a_car_is_imported_whatever_the_pieces_it_arrives_in(store: ContentStore) -> None:
    """A part is read as it arrives: a varint, a CID or a block may be cut across writes."""
    blocks, root = import_bytes(os.urandom(300_000), ImportParams(chunk_size=10_000))
    car = b"".join(write_car([root], blocks))
    car_import = CarImport(store, pin_roots=True)
    try:
        car_import.begin("pieces.car")
        at = 0
        for size in itertools.cycle([1, 2, 3, 5, 8, 13, 9_999, 70_001]):
            if at >= len(car):
                break
            car_import.write(car[at : at + size])
            at += size
        car_import.end()
        assert car_import.commit(ALICE) == [ImportedRoot(root, "")]
    finally:
        car_import.discard()
    assert (car_import.stats.blocks, car_import.stats.bytes) == (
        len(blocks),
        sum(len(block.data) for block in blocks),
    )
    assert store.usage()[0] == len(blocks)
    assert reading_threads() == []


def writes_until_refused(
    car_import: CarImport, data: bytes, most: int
) -> tuple[int, CarRejected | None]:
    """How many writes of ``data`` went through before one was refused, and the refusal."""
    for written in range(most):
        try:
            car_import.write(data)
        except CarRejected as refused:
            return written, refused
    return most, None


def test_a_bad_block_stops_the_upload_before_the_rest_of_the_car_arrives(
    store: ContentStore,
) -> None:
    """The part used to be spooled whole before a block was read: a bad first block of a
    CAR of any size was found once every byte had arrived and been written to disk."""
    claimed = CID.from_block(b"what the CID says", RAW, 1)
    head = b"".join(write_car([claimed], [Block(claimed, b"what the CAR holds")]))
    rest = bytes(1 << 20)
    car_import = CarImport(store, pin_roots=True)
    try:
        car_import.begin("bad.car")
        car_import.write(head)
        written, refused = writes_until_refused(car_import, rest, most=32)
    finally:
        car_import.discard()
    assert f"does not match CID {claimed}" in str(refused)
    assert written * len(rest) <= PIPE_BYTES + 2 * BATCH_BYTES
    assert store.usage() == (0, 0)
    assert reading_threads() == []


def test_a_body_cut_short_stops_the_reader_and_stores_nothing(store: ContentStore) -> None:
    """The client went away in the middle of a part: the reader waiting for the rest is
    stopped, and the blocks it had staged are dropped with the staging."""
    blocks, root = import_bytes(os.urandom(200_000), ImportParams(chunk_size=10_000))
    car = b"".join(write_car([root], blocks))
    car_import = CarImport(store, pin_roots=True)
    car_import.begin("cut.car")
    car_import.write(car[: len(car) // 2])
    car_import.discard()
    assert reading_threads() == []
    assert store.usage() == (0, 0)
    assert list(car_import.staging.directory.iterdir()) == []


def test_what_follows_a_carv2_payload_is_neither_read_nor_waited_for(
    store: ContentStore,
) -> None:
    """The reader stops at the payload's end; the bytes after it (an index) still arrive and
    are dropped, never held: three pipes' worth of them must not block the upload."""
    blocks, root = import_bytes(os.urandom(50_000), ImportParams(chunk_size=10_000))
    v2 = carv2(b"".join(write_car([root], blocks)), tail=bytes(3 * PIPE_BYTES))
    car_import = CarImport(store, pin_roots=True)
    try:
        car_import.begin("v2.car")
        for at in range(0, len(v2), BATCH_BYTES):
            car_import.write(v2[at : at + BATCH_BYTES])
        car_import.end()
        assert car_import.commit(ALICE) == [ImportedRoot(root, "")]
    finally:
        car_import.discard()
    assert store.usage()[0] == len(blocks)
