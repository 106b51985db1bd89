"""The record store: all-or-nothing batches, authorship, views rebuilt from the log."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pytest
from tinydb import TinyDB

from robocloud.proofs import RecordIdError
from robocloud.templates import canonical_record, parse_template
from services.storage import segments
from services.storage.recordlog import CHUNK
from services.storage.recordstore import (
    OffloadFailed,
    RecordNotFound,
    RecordRejected,
)
from services.storage.segments import (
    MANIFEST,
    TABLE,
    DocumentForm,
    PreparedDocuments,
    SegmentStorage,
)
from tests.unit.services.ledger.crash import output_of_killed
from tests.unit.services.storage.conftest import (
    AUTHOR,
    ROBOT_A,
    STATE,
    StoreFactory,
    approve,
    state_record,
)


def test_a_batch_is_logged_indexed_and_read_back(open_store: StoreFactory) -> None:
    store = open_store()
    ids = store.append([state_record(t) for t in range(40)], author=AUTHOR)
    assert ids == [f"state-1-{n}" for n in range(40)]
    views = store.views("state@1")
    assert views is not None
    assert (views.durable, len(views.tail)) == (32, 8)
    stored = store.get("state-1-17")
    assert stored.record == json.loads(json.dumps(state_record(17)))
    assert stored.meta["signer"] == ROBOT_A
    assert stored.meta["request_sha256"] == AUTHOR.request_sha256
    assert [doc["_i"] for doc in views.docs(views.sealed[1])] == list(range(16, 32))
    assert views.docs(views.sealed[0])[3]["pose.x"] == 3


def test_a_bad_record_refuses_the_whole_batch(open_store: StoreFactory) -> None:
    store = open_store()
    store.append([state_record(0)], author=AUTHOR)
    batch = [state_record(1), state_record(2), state_record(3, pose={"x": "far", "y": 0})]
    with pytest.raises(RecordRejected) as rejected:
        store.append(batch, author=AUTHOR)
    assert (rejected.value.index, rejected.value.path) == (2, "data.pose.x")
    unknown = {**state_record(4), "template": "gps@1"}
    with pytest.raises(RecordRejected) as missing:
        store.append([state_record(5), unknown], author=AUTHOR)
    assert (missing.value.index, missing.value.code) == (1, "template_not_found")
    store.catalog.create({"name": "gps", "fields": {"lat": "float"}}, author=ROBOT_A)
    draft = {**state_record(4), "template": "gps@1", "data": {"lat": 1.0}}
    with pytest.raises(RecordRejected) as unapproved:
        store.append([draft], author=AUTHOR)
    assert unapproved.value.code == "template_not_approved"
    assert store.logs.size("state@1") == 1
    assert store.logs.template_ids() == ["state@1"]


def test_a_large_array_without_cas_stores_nothing(open_store: StoreFactory) -> None:
    store = open_store()
    large = state_record(1, ranges=[float(n) for n in range(200)])
    with pytest.raises(OffloadFailed) as failed:
        store.append([state_record(0), large], author=AUTHOR)
    assert (failed.value.index, failed.value.path) == (1, "data.ranges")
    assert store.logs.size("state@1") == 0


def test_views_are_rebuilt_past_their_mark(open_store: StoreFactory) -> None:
    store = open_store()
    store.append([state_record(t) for t in range(40)], author=AUTHOR)
    views = store.views("state@1")
    assert views is not None
    directory = views.directory
    (directory / "seg-000000000048.json").write_text("{half a segment")
    manifest = json.loads((directory / MANIFEST).read_bytes())
    manifest["sealed"] = manifest["sealed"][:1]
    (directory / MANIFEST).write_text(json.dumps(manifest))
    store = open_store()
    views = store.views("state@1")
    assert views is not None
    assert not (directory / "seg-000000000048.json").exists()
    assert (views.durable, len(views.tail)) == (32, 8)
    assert [doc["_i"] for doc in views.all_docs()] == list(range(40))
    assert store.append([state_record(40)], author=AUTHOR) == ["state-1-40"]


def test_record_ids(open_store: StoreFactory) -> None:
    store = open_store()
    for bad in ("state-1", "state-01-2", "State-1-2", "state-1-02", "state-1--1"):
        with pytest.raises(RecordIdError):
            store.get(bad)
    with pytest.raises(RecordNotFound):
        store.get("state-1-0")
    with pytest.raises(RecordNotFound):
        store.get("gps-1-0")


def test_a_time_in_epoch_nanoseconds_is_stored_and_proved_exactly(open_store: StoreFactory) -> None:
    """Real recordings stamp records near 1.7e18 ns, past the integers RFC 8785 holds."""
    store = open_store()
    t = 1_700_000_000_123_456_789
    (record_id,) = store.append([state_record(t)], author=AUTHOR)
    stored = store.get(record_id)
    assert stored.record["t"] == t
    entry = store.logs.entry("state@1", 0)
    assert b'"t":1700000000123456789' in entry.record
    assert entry.record == canonical_record(stored.record)


def test_decoded_segments_in_memory_are_bounded(open_store: StoreFactory) -> None:
    """Sealing and reading many segments keeps the documents of ``segment_cache`` (4) only;
    an evicted segment is read back from its file, equal to what was sealed."""
    store = open_store()
    store.append([state_record(t) for t in range(16 * 12)], author=AUTHOR)
    store.index_keywords()
    views = store.views("state@1")
    assert views is not None
    assert len(views.sealed) == 12
    for segment in views.sealed:
        views.index(segment, "_t")
    assert len(store.caches.docs) == 4
    assert len(store.caches.indexes) == 12
    first = views.docs(views.sealed[0])
    assert [doc["_t"] for doc in first] == list(range(16))
    assert len(store.caches.docs) == 4


def test_a_sealed_segment_is_the_file_tinydb_itself_writes(
    open_store: StoreFactory, tmp_path: Path
) -> None:
    """A segment is written in one call of TinyDB's storage; the file equals, byte for byte,
    the one TinyDB's ``insert_multiple`` writes into a fresh database from the same documents,
    and each sorted index is Python's stable sort of its values (ties in position order)."""
    store = open_store()
    records = [state_record(t % 5, pose={"x": t % 3, "y": 0.5}) for t in range(16)]
    store.append(records, author=AUTHOR)
    views = store.views("state@1")
    assert views is not None
    segment = views.sealed[0]
    docs = views.docs(segment)
    reference = TinyDB(tmp_path / "reference.json", storage=SegmentStorage)
    reference.table(TABLE).insert_multiple(docs)
    reference.close()
    sealed = views.directory / f"{segment.name}.json"
    assert sealed.read_bytes() == (tmp_path / "reference.json").read_bytes()
    for field in ("_t", "pose.x"):
        index = views.index(segment, field)
        order = sorted(range(16), key=lambda n: docs[n][field])
        assert list(index.positions) == order
        assert list(index.values) == [docs[n][field] for n in order]


def test_a_template_without_numbers_prepares_rows_of_its_time_alone() -> None:
    """A record of strings only is indexed by its time alone: its row is ``_t``."""
    form = DocumentForm(
        parse_template({"name": "note", "version": 1, "fields": {"text": "string"}})
    )
    record = {"template": "note@1", "topic": "/notes", "robot": ROBOT_A, "t": 7, "data": {}}
    record["data"] = {"text": "docked at 3"}
    doc, row, text = form.prepared(canonical_record(record))
    assert json.loads(doc) == {
        "_i": 0,
        "_t": 7,
        "_topic": "/notes",
        "_robot": ROBOT_A,
        "text": "docked at 3",
    }
    assert text == "docked at 3"
    assert [column.tolist() for column in form.columns(row + row)] == [[7, 7]]


def test_an_ingest_batch_fits_the_segments(open_store: StoreFactory) -> None:
    """Segments of 16 records with 5 in the tail: a batch of up to 50 ends on a boundary, 43
    records (11 to complete the tail, two whole segments); one too short for a boundary is
    taken whole."""
    store = open_store()
    store.append([state_record(t) for t in range(5)], author=AUTHOR)
    assert store.fitting("state@1", 50) == 43
    assert store.fitting("state@1", 11) == 11
    assert store.fitting("state@1", 10) == 10
    store.append([state_record(t) for t in range(11)], author=AUTHOR)
    assert store.fitting("state@1", 50) == 48


ARM = {**STATE, "name": "arm"}


def two_template_batch(start: int) -> list[dict[str, object]]:
    """Five records of arm@1, then seven of state@1: one request, two logs."""
    arm = [{**state_record(t), "template": "arm@1"} for t in range(start, start + 5)]
    return arm + [state_record(t) for t in range(start, start + 7)]


CRASHING_WRITER = """
import os, signal, sys
from pathlib import Path
from services.storage.catalog import Catalog
from services.storage.recordlog import RecordLogs
from services.storage.recordstore import RecordStore
from tests.unit.services.storage.conftest import AUTHOR, STATE, approve
from tests.unit.services.storage.test_recordstore import ARM, two_template_batch

root = Path(sys.argv[1])
catalog = Catalog(root / "catalog")
approve(catalog, STATE)
approve(catalog, ARM)
store = RecordStore(root, RecordLogs(root / "logs"), catalog, segment_records=16)
store.append(two_template_batch(0), author=AUTHOR)
print("acknowledged", flush=True)
synced = os.fdatasync

def dying(fd):
    synced(fd)
    if os.readlink(f"/proc/self/fd/{fd}").endswith("/arm@1/index.bin"):
        os.kill(os.getpid(), signal.SIGKILL)

os.fdatasync = dying
store.append(two_template_batch(100), author=AUTHOR)
print("not acknowledged", flush=True)
"""


def test_a_batch_over_two_templates_killed_between_their_logs_is_stored_whole_or_not_at_all(
    tmp_path: Path, open_store: StoreFactory
) -> None:
    assert output_of_killed(CRASHING_WRITER, tmp_path) == "acknowledged\n"
    store = open_store()
    assert store.logs.sizes() == {"arm@1": 5, "state@1": 7}
    with pytest.raises(RecordNotFound):
        store.get("arm-1-5")
    ids = store.append(two_template_batch(200), author=AUTHOR)
    assert ids == [f"arm-1-{n}" for n in range(5, 10)] + [f"state-1-{n}" for n in range(7, 14)]
    assert store.get("arm-1-5").record["t"] == 200
    assert [views.size for views in (store.views("arm@1"), store.views("state@1")) if views] == [
        10,
        14,
    ]


def failing_sync(path_suffix: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """``os.fdatasync`` of a file whose path ends with ``path_suffix`` fails with EIO."""
    synced = os.fdatasync

    def failing(fd: int) -> None:
        if os.readlink(f"/proc/self/fd/{fd}").endswith(path_suffix):
            raise OSError(errno.EIO, "Input/output error")
        synced(fd)

    monkeypatch.setattr(os, "fdatasync", failing)


def test_a_batch_whose_second_log_fails_leaves_the_first_unchanged(
    open_store: StoreFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = open_store()
    approve(store.catalog, ARM)
    store.append(two_template_batch(0), author=AUTHOR)
    failing_sync("/state@1/index.bin", monkeypatch)
    with pytest.raises(OSError, match="Input/output error"):
        store.append(two_template_batch(100), author=AUTHOR)
    monkeypatch.undo()
    assert store.logs.sizes() == {"arm@1": 5, "state@1": 7}
    assert store.append(two_template_batch(200), author=AUTHOR)[0] == "arm-1-5"
    store = open_store()
    assert store.logs.sizes() == {"arm@1": 10, "state@1": 14}
    assert [store.get(f"arm-1-{n}").record["t"] for n in (4, 5)] == [4, 200]


def test_a_batch_whose_chunk_hashes_cannot_be_saved_is_stored_and_shown_whole(
    open_store: StoreFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Saving the chunk hashes of a log after its batch committed failed with EIO, with the
    first log shown and the second not: the second's later appends wrote over its
    committed entries, and its stale tail came back at the next open."""
    store = open_store()
    approve(store.catalog, ARM)
    arm = [{**state_record(t), "template": "arm@1"} for t in range(CHUNK - 1)]
    store.append(arm, author=AUTHOR)
    failing_sync("/arm@1/subtrees.bin", monkeypatch)
    ids = store.append(two_template_batch(1000), author=AUTHOR)
    assert (ids[0], ids[-1]) == (f"arm-1-{CHUNK - 1}", "state-1-6")
    assert store.logs.sizes() == {"arm@1": CHUNK + 4, "state@1": 7}
    assert store.append([state_record(2000)], author=AUTHOR) == ["state-1-7"]
    monkeypatch.undo()
    root = store.logs.root("arm@1", CHUNK)
    store = open_store()
    assert store.logs.sizes() == {"arm@1": CHUNK + 4, "state@1": 8}
    assert store.logs.root("arm@1", CHUNK) == root
    assert [store.get(f"state-1-{n}").record["t"] for n in (6, 7)] == [1006, 2000]


def full_disk_under(directory_part: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Segment files whose path names ``directory_part`` cannot be written: ENOSPC."""
    real = segments.write_synced

    def refusing(path: Path, data: bytes, *, mode: int = 0o644) -> None:
        if directory_part in str(path):
            raise OSError(errno.ENOSPC, "No space left on device")
        real(path, data, mode=mode)

    monkeypatch.setattr(segments, "write_synced", refusing)


def test_a_segment_the_disk_cannot_take_leaves_the_request_stored_and_acknowledged(
    open_store: StoreFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The log committed, then arm@1's segment hit a full disk: the request was answered 500
    though stored (a retry stored it twice), and state@1's views never got their part, so
    every later write to state@1 was stored and then refused until a restart."""
    store = open_store()
    approve(store.catalog, ARM)
    store.append([{**state_record(t), "template": "arm@1"} for t in range(14)], author=AUTHOR)
    full_disk_under("arm@1", monkeypatch)
    ids = store.append(two_template_batch(100), author=AUTHOR)
    assert ids[:2] == ["arm-1-14", "arm-1-15"]
    arm, state = store.views("arm@1"), store.views("state@1")
    assert arm is not None
    assert state is not None
    assert (arm.size, arm.durable, state.size) == (19, 0, 7)
    assert store.append([state_record(200)], author=AUTHOR) == ["state-1-7"]
    monkeypatch.undo()
    assert store.append([{**state_record(300), "template": "arm@1"}], author=AUTHOR) == ["arm-1-19"]
    assert (arm.size, arm.durable) == (20, 16)
    assert [doc["_t"] for doc in arm.docs(arm.sealed[0])][-2:] == [100, 101]
    store = open_store()
    assert store.logs.sizes() == {"arm@1": 20, "state@1": 8}


def test_prepared_records_a_segment_write_refuses_are_held_in_the_tail(
    open_store: StoreFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An ingest batch whose second whole segment hit a full disk kept none of the records
    from there on, so the views stayed behind the log and refused every later write."""
    store = open_store()
    store.append([state_record(t) for t in range(5)], author=AUTHOR)
    views = store.views("state@1")
    assert views is not None
    prepared = [views.form.prepared(canonical_record(state_record(t))) for t in range(5, 48)]
    documents = PreparedDocuments(
        [doc + b"\n" for doc, _, _ in prepared],
        b"".join(row for _, row, _ in prepared),
        views.form.row.size,
    )
    full_disk_under(f"seg-{32:012d}", monkeypatch)
    with pytest.raises(OSError, match="No space"):
        views.add_prepared(5, documents)
    assert (views.size, views.durable) == (48, 32)
    monkeypatch.undo()
    views.add([views.flatten(state_record(48), 48)])
    assert (views.size, views.durable) == (49, 48)
    assert [doc["_t"] for doc in views.docs(views.sealed[2])] == list(range(32, 48))
