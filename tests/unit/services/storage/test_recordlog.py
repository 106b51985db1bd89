"""The record logs: durable appends, RFC 6962 roots and proofs, recovery from a torn tail."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest

from robocloud import merkle
from services.storage.recordlog import (
    BATCH_JOURNAL,
    CHUNK,
    INDEX_ENTRY,
    EntryNotFound,
    InvalidTemplateId,
    InvalidTreeSize,
    LogEntry,
    RecordLogs,
)
from tests.unit.services.ledger.crash import acknowledged_before_kill

IMU = "imu@1"


def entry(i: int, template: str = IMU) -> LogEntry:
    record = json.dumps({"data": {"i": i}, "template": template}, separators=(",", ":"))
    return LogEntry(record=record.encode(), meta=json.dumps({"signer": f"s{i}"}).encode())


def entries(start: int, stop: int, template: str = IMU) -> list[LogEntry]:
    return [entry(i, template) for i in range(start, stop)]


def leaves(start: int, stop: int) -> list[bytes]:
    return [merkle.leaf_hash(e.record) for e in entries(start, stop)]


def test_appends_return_first_indexes_and_read_back(tmp_path: Path) -> None:
    logs = RecordLogs(tmp_path)
    assert logs.append(IMU, entries(0, 3)) == 0
    assert logs.append(IMU, entries(3, 5)) == 3
    assert logs.append("gps@2", entries(0, 1, "gps@2")) == 0
    assert logs.append(IMU, []) == 5
    assert logs.size(IMU) == 5
    assert logs.size("gps@2") == 1
    assert logs.size("never@1") == 0
    assert logs.template_ids() == ["gps@2", IMU]
    assert logs.sizes() == {"gps@2": 1, IMU: 5}
    assert logs.entry(IMU, 4) == entry(4)
    assert list(logs.entries(IMU, 1, 4)) == entries(1, 4)
    assert list(logs.entries(IMU, 2, 100)) == entries(2, 5)
    assert list(logs.entries("never@1", 0, 10)) == []
    logs.close()
    reopened = RecordLogs(tmp_path)
    assert list(reopened.entries(IMU, 0, 5)) == entries(0, 5)
    assert reopened.entry("gps@2", 0) == entry(0, "gps@2")


def test_entries_cross_read_batches(tmp_path: Path) -> None:
    logs = RecordLogs(tmp_path)
    logs.append(IMU, entries(0, 5000))
    assert list(logs.entries(IMU, 10, 4500)) == entries(10, 4500)


def test_roots_and_proofs_match_the_reference_tree_across_chunks(tmp_path: Path) -> None:
    logs = RecordLogs(tmp_path)
    total = 3 * CHUNK + 17
    for start in range(0, total, 97):
        logs.append(IMU, entries(start, min(start + 97, total)))
    reference = merkle.MerkleTree(leaves(0, total))
    sizes = [1, 2, 3, CHUNK - 1, CHUNK, CHUNK + 1, 2 * CHUNK, 3 * CHUNK, total]
    for size in sizes:
        assert logs.root(IMU, size) == reference.root(size)
        for index in {0, size // 2, size - 1}:
            proof = logs.inclusion_proof(IMU, index, size)
            assert proof == reference.inclusion_proof(index, size)
            merkle.verify_inclusion(
                index, size, reference.leaves[index], proof, reference.root(size)
            )
        for first in {1, size // 3, size - 1}:
            if 0 < first < size:
                consistency = logs.consistency_proof(IMU, first, size)
                assert consistency == reference.consistency_proof(first, size)
                merkle.verify_consistency(
                    first, size, reference.root(first), reference.root(size), consistency
                )
    assert logs.root(IMU, 0) == merkle.EMPTY_ROOT
    assert logs.root("never@1", 0) == merkle.EMPTY_ROOT
    logs.close()
    assert RecordLogs(tmp_path).root(IMU, total) == reference.root()


def test_proofs_in_a_log_of_many_chunk_levels_verify(tmp_path: Path) -> None:
    logs = RecordLogs(tmp_path)
    total = 70_001
    logs.append(IMU, entries(0, total))
    all_leaves = leaves(0, total)
    head = merkle.root(all_leaves)
    assert logs.root(IMU, total) == head
    for index in (0, 1, CHUNK, 65_535, 65_536, total - 1):
        merkle.verify_inclusion(
            index, total, all_leaves[index], logs.inclusion_proof(IMU, index, total), head
        )
    for first in (1, CHUNK, 40_000, 65_536, total - 1):
        merkle.verify_consistency(
            first,
            total,
            merkle.root(all_leaves[:first]),
            head,
            logs.consistency_proof(IMU, first, total),
        )


@pytest.mark.parametrize("template_id", ["../etc@1", "Imu@1", "imu@0", "imu", "imu@1/x", ""])
def test_a_malformed_template_id_is_refused_and_nothing_is_created(
    tmp_path: Path, template_id: str
) -> None:
    logs = RecordLogs(tmp_path / "logs")
    with pytest.raises(InvalidTemplateId) as refused:
        logs.append(template_id, entries(0, 1))
    assert refused.value.template_id == template_id
    with pytest.raises(InvalidTemplateId):
        logs.size(template_id)
    assert [p.name for p in (tmp_path / "logs").iterdir()] == [BATCH_JOURNAL]
    assert (tmp_path / "logs" / BATCH_JOURNAL).read_bytes() == b""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["logs"]


def test_out_of_range_indexes_and_sizes_are_refused(tmp_path: Path) -> None:
    logs = RecordLogs(tmp_path)
    logs.append(IMU, entries(0, 4))
    with pytest.raises(EntryNotFound) as missing:
        logs.entry(IMU, 4)
    assert (missing.value.index, missing.value.size) == (4, 4)
    with pytest.raises(EntryNotFound):
        logs.entry(IMU, -1)
    with pytest.raises(EntryNotFound):
        logs.entry("never@1", 0)
    with pytest.raises(InvalidTreeSize):
        logs.root(IMU, 5)
    with pytest.raises(EntryNotFound):
        logs.inclusion_proof(IMU, 4, 4)
    with pytest.raises(InvalidTreeSize):
        logs.inclusion_proof(IMU, 0, 5)
    with pytest.raises(InvalidTreeSize):
        logs.consistency_proof(IMU, 3, 2)
    with pytest.raises(InvalidTreeSize):
        logs.consistency_proof(IMU, 1, 9)
    with pytest.raises(InvalidTreeSize):
        list(logs.entries(IMU, 3, 1))
    assert logs.size(IMU) == 4
    assert logs.consistency_proof(IMU, 0, 4) == []
    assert logs.consistency_proof(IMU, 4, 4) == []


def reopen_after(tmp_path: Path, damage: str) -> RecordLogs:
    """Five durable entries, then the damage a crash mid-append leaves, then a new open."""
    logs = RecordLogs(tmp_path)
    logs.append(IMU, entries(0, 5))
    logs.close()
    directory = tmp_path / IMU
    records = directory / "records.log"
    index = directory / "index.bin"
    if damage == "frame cut before its index entry":
        with records.open("ab") as file:
            file.write(b'\x00\x00\x00\x40\x00\x00\x00\x02{"data":')
    elif damage == "index entry cut":
        with records.open("ab") as file:
            file.write(b"\x00\x00\x00\x02\x00\x00\x00\x00{}")
        with index.open("ab") as file:
            file.write(INDEX_ENTRY.pack(records.stat().st_size - 10, b"\x00" * 32)[:17])
    elif damage == "indexed frame cut":
        with records.open("r+b") as file:
            file.truncate(records.stat().st_size - 3)
    elif damage == "index entry of zeros":
        with index.open("ab") as file:
            file.write(b"\x00" * INDEX_ENTRY.size)
    return RecordLogs(tmp_path)


@pytest.mark.parametrize(
    ("damage", "kept"),
    [
        ("frame cut before its index entry", 5),
        ("index entry cut", 5),
        ("index entry of zeros", 5),
        ("indexed frame cut", 4),
    ],
)
def test_a_torn_tail_is_truncated_at_open(tmp_path: Path, damage: str, kept: int) -> None:
    logs = reopen_after(tmp_path, damage)
    assert logs.size(IMU) == kept
    assert list(logs.entries(IMU, 0, 10)) == entries(0, kept)
    assert logs.append(IMU, entries(kept, 8)) == kept
    assert list(logs.entries(IMU, 0, 10)) == entries(0, 8)
    assert logs.root(IMU, 8) == merkle.root(leaves(0, 8))
    logs.close()
    assert RecordLogs(tmp_path).root(IMU, 8) == merkle.root(leaves(0, 8))


@pytest.mark.parametrize("damage", ["cut", "zeroed", "missing"])
def test_chunk_hashes_are_checked_and_rebuilt_at_open(tmp_path: Path, damage: str) -> None:
    total = 3 * CHUNK + 5
    logs = RecordLogs(tmp_path)
    logs.append(IMU, entries(0, total))
    logs.close()
    subtrees = tmp_path / IMU / "subtrees.bin"
    assert subtrees.stat().st_size == 3 * merkle.HASH_SIZE
    if damage == "cut":
        with subtrees.open("r+b") as file:
            file.truncate(merkle.HASH_SIZE + 7)
    elif damage == "zeroed":
        with subtrees.open("r+b") as file:
            file.seek(2 * merkle.HASH_SIZE)
            file.write(b"\x00" * merkle.HASH_SIZE)
    else:
        subtrees.unlink()
    reopened = RecordLogs(tmp_path)
    assert reopened.root(IMU, total) == merkle.root(leaves(0, total))
    assert subtrees.stat().st_size == 3 * merkle.HASH_SIZE


def test_concurrent_appends_get_distinct_indexes(tmp_path: Path) -> None:
    logs = RecordLogs(tmp_path)
    firsts: list[int] = []

    def writer(base: int) -> None:
        for batch in range(10):
            start = base * 1000 + batch * 10
            firsts.append(logs.append(IMU, entries(start, start + 10)))

    threads = [threading.Thread(target=writer, args=(n,)) for n in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(firsts) == list(range(0, 400, 10))
    stored = list(logs.entries(IMU, 0, 400))
    assert sorted(stored, key=lambda e: e.record) == sorted(
        [entry(b * 1000 + i) for b in range(4) for i in range(100)], key=lambda e: e.record
    )
    assert logs.root(IMU, 400) == merkle.root([merkle.leaf_hash(e.record) for e in stored])


WRITER = """
import json, sys
from pathlib import Path
from services.storage.recordlog import LogEntry, RecordLogs

logs = RecordLogs(Path(sys.argv[1]))
i = 0
while True:
    batch = [
        LogEntry(json.dumps({"i": i + k}).encode(), b'{"m":' + str(i + k).encode() + b"}")
        for k in range(37)
    ]
    first = logs.append("imu@1", batch)
    print(first, len(batch), flush=True)
    i += len(batch)
"""


def test_every_append_acknowledged_before_kill_9_survives(tmp_path: Path) -> None:
    acknowledged = acknowledged_before_kill(WRITER, tmp_path, 40)
    logs = RecordLogs(tmp_path)
    size = logs.size(IMU)
    last_first, last_count = (int(part) for part in acknowledged[-1].split())
    assert size >= last_first + last_count
    stored = list(logs.entries(IMU, 0, size))
    assert [json.loads(e.record) for e in stored] == [{"i": i} for i in range(size)]
    assert [e.meta for e in stored] == [b'{"m":%d}' % i for i in range(size)]
    assert logs.root(IMU, size) == merkle.root([merkle.leaf_hash(e.record) for e in stored])
    assert logs.append(IMU, [LogEntry(b'{"i":"after"}', b"{}")]) == size


GPS = "gps@1"


def test_a_batch_over_logs_whose_index_reached_the_disk_in_part_is_undone_at_open(
    tmp_path: Path,
) -> None:
    logs = RecordLogs(tmp_path)
    assert logs.append_batch({IMU: entries(0, 3), GPS: entries(0, 4, GPS)}) == {IMU: 0, GPS: 0}
    assert logs.append_batch({IMU: entries(3, 5), GPS: entries(4, 9, GPS)}) == {IMU: 3, GPS: 4}
    logs.close()
    with (tmp_path / GPS / "index.bin").open("r+b") as index:
        index.truncate(6 * INDEX_ENTRY.size + 11)
    reopened = RecordLogs(tmp_path)
    assert reopened.sizes() == {GPS: 4, IMU: 3}
    assert list(reopened.entries(IMU, 0, 10)) == entries(0, 3)
    assert reopened.root(GPS, 4) == merkle.root(
        [merkle.leaf_hash(e.record) for e in entries(0, 4, GPS)]
    )
    assert reopened.append_batch({IMU: entries(3, 4)}) == {IMU: 3}
    reopened.close()
    assert RecordLogs(tmp_path).sizes() == {GPS: 4, IMU: 4}


def test_one_log_whose_batch_index_is_cut_loses_the_whole_batch(tmp_path: Path) -> None:
    logs = RecordLogs(tmp_path)
    logs.append(IMU, entries(0, 5))
    logs.append(IMU, entries(5, 10))
    logs.close()
    with (tmp_path / IMU / "index.bin").open("r+b") as index:
        index.truncate(7 * INDEX_ENTRY.size)
    reopened = RecordLogs(tmp_path)
    assert reopened.size(IMU) == 5
    assert reopened.root(IMU, 5) == merkle.root(leaves(0, 5))


@pytest.mark.parametrize("journal", [b"", b"\x00" * 40, b"torn"])
def test_a_torn_or_empty_journal_undoes_nothing(tmp_path: Path, journal: bytes) -> None:
    logs = RecordLogs(tmp_path)
    logs.append_batch({IMU: entries(0, 3), GPS: entries(0, 4, GPS)})
    logs.close()
    (tmp_path / BATCH_JOURNAL).write_bytes(journal)
    assert RecordLogs(tmp_path).sizes() == {GPS: 4, IMU: 3}


TWO_LOG_WRITER = """
import json, sys
from pathlib import Path
from services.storage.recordlog import LogEntry, RecordLogs

logs = RecordLogs(Path(sys.argv[1]))
batch = 0
while True:
    logs.append_batch({
        "imu@1": [LogEntry(json.dumps([batch, k]).encode(), b"{}") for k in range(37)],
        "gps@1": [LogEntry(json.dumps([batch, k]).encode(), b"{}") for k in range(11)],
    })
    print(batch, flush=True)
    batch += 1
"""


def test_batches_over_two_logs_acknowledged_before_kill_9_survive_whole(tmp_path: Path) -> None:
    acknowledged = acknowledged_before_kill(TWO_LOG_WRITER, tmp_path, 30)
    logs = RecordLogs(tmp_path)
    sizes = logs.sizes()
    batches = sizes[IMU] // 37
    assert batches > int(acknowledged[-1])
    assert sizes == {IMU: 37 * batches, GPS: 11 * batches}
    assert [json.loads(e.record) for e in logs.entries(GPS, 0, sizes[GPS])] == [
        [b, k] for b in range(batches) for k in range(11)
    ]
