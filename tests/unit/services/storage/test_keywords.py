"""The keyword index: one document per distinct text of a batch, its records as runs."""

from __future__ import annotations

import contextlib
import gc
import json
import logging
import os
import threading
from collections.abc import Callable
from functools import partialmethod
from itertools import pairwise
from pathlib import Path
from typing import Any

import pytest
import whoosh.searching
import whoosh.writing
from hypothesis import given
from hypothesis import strategies as st

from robocloud.templates import parse_template
from services.storage import keywords
from services.storage.keywords import KeywordIndex, TooManyKeywordHits, parse_runs, runs
from services.storage.segments import keyword_text
from tests.unit.services.storage.conftest import AUTHOR, StoreFactory, approve, state_record


@given(st.sets(st.integers(0, 5_000), min_size=1))
def test_runs_round_trip(indexes: set[int]) -> None:
    ordered = sorted(indexes)
    spans = parse_runs(runs(ordered))
    assert [index for span in spans for index in span] == ordered
    assert all(left.stop < right.start for left, right in pairwise(spans))


def test_runs_are_compact() -> None:
    assert runs([0, 1, 2, 3, 7, 9, 10]) == "0-3,7,9-10"


def test_repeated_texts_share_a_document_and_every_record_is_found(tmp_path: Path) -> None:
    index = KeywordIndex(tmp_path)
    texts = ["DOCKED base" if i % 3 == 0 else "moving base" for i in range(30)]
    index.add("state@1", 0, texts, 30)
    index.add("state@1", 30, ["DOCKED dock_2"], 31)
    with index.index.searcher() as searcher:
        assert searcher.doc_count() == 3
    assert index.search(["docked"], None) == {"state@1": {*range(0, 30, 3), 30}}
    assert index.search(["moving", "base"], "state@1") == {
        "state@1": {i for i in range(30) if i % 3}
    }
    assert index.search(["docked"], "other@1") == {}
    assert index.mark("state@1") == 31
    index.close()


def test_a_batch_indexed_again_after_a_crash_replaces_its_documents(tmp_path: Path) -> None:
    """A crash between the commit and the mark replays the batch from the same start."""
    index = KeywordIndex(tmp_path)
    index.add("state@1", 0, ["idle", "idle"], 2)
    index.add("state@1", 0, ["idle", "idle", "idle"], 3)
    with index.index.searcher() as searcher:
        assert searcher.doc_count() == 1
    assert index.search(["idle"], None) == {"state@1": {0, 1, 2}}
    index.close()
    reopened = KeywordIndex(tmp_path)
    assert reopened.mark("state@1") == 3
    assert reopened.search(["idle"], None) == {"state@1": {0, 1, 2}}
    reopened.close()


def test_only_a_batch_that_may_repeat_an_attempt_replaces_by_key(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A key lookup a document is a fifth of a commit: a template's first batch since the
    index was opened may repeat a commit whose mark was lost, and so may a batch retried
    after its commit's fsync failed; a batch past a mark this process wrote may not."""
    index = KeywordIndex(tmp_path)
    replaced: list[str] = []
    update_document = whoosh.writing.SegmentWriter.update_document

    def counted(writer: whoosh.writing.SegmentWriter, **fields: str) -> None:
        replaced.append(fields["key"])
        update_document(writer, **fields)

    monkeypatch.setattr(whoosh.writing.SegmentWriter, "update_document", counted)
    index.add("state@1", 0, ["idle", "docked"], 2)
    index.add("state@1", 2, ["idle"], 3)
    assert [key.split("/")[1] for key in replaced] == ["0", "0"]
    fsync = os.fsync

    def failing(fd: int) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "fsync", failing)
    with pytest.raises(OSError, match="Input/output error"):
        index.add("state@1", 3, ["moving"], 4)
    monkeypatch.setattr(os, "fsync", fsync)
    index.add("state@1", 3, ["moving"], 4)
    assert [key.split("/")[1] for key in replaced] == ["0", "0", "3"]
    with index.index.searcher() as searcher:
        assert searcher.doc_count() == 4
    assert index.search(["moving"], None) == {"state@1": {3}}
    assert index.mark("state@1") == 4
    index.close()


def test_a_query_matching_too_many_records_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(keywords, "MAX_HITS", 10)
    index = KeywordIndex(tmp_path)
    index.add("state@1", 0, ["idle"] * 11, 11)
    with pytest.raises(TooManyKeywordHits, match="more than 10 records"):
        index.search(["idle"], None)
    index.close()


def held_open(directory: Path) -> list[str]:
    """The files under ``directory`` this process holds open or mapped, deleted ones too."""
    held = []
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):
            held.append(os.readlink(f"/proc/self/fd/{fd}"))
    with open("/proc/self/maps") as maps:
        held += [line.split(maxsplit=5)[-1].strip() for line in maps]
    return [path for path in held if path.startswith(str(directory))]


def test_commits_and_searches_leave_no_file_of_the_index_open(tmp_path: Path) -> None:
    """Whoosh's merges and its writer's key lookups close their segment readers while
    mapped views are still exported from them, so a mapped segment stayed open until the
    cyclic collector ran: hundreds of descriptors, and merged-away segments kept on disk
    though deleted, under a node's large heap. Nothing waits for the collector here."""
    index = KeywordIndex(tmp_path)
    gc.disable()
    try:
        for batch in range(8):
            texts = [f"pose{batch} frame_{n % 3}" for n in range(20)]
            index.add("state@1", batch * 20, texts, (batch + 1) * 20)
            assert index.search(["frame_1"], None)["state@1"]
        assert held_open(tmp_path) == []
    finally:
        gc.enable()
    assert index.search(["pose7", "frame_2"], "state@1") == {
        "state@1": {140 + n for n in range(20) if n % 3 == 2}
    }
    index.close()


def _fsyncs_and_replaces(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, str]]:
    """Record ("fsync", path) and ("replace", target) in the order they happen."""
    calls: list[tuple[str, str]] = []
    fsync, replace = os.fsync, os.replace

    def recording_fsync(fd: int) -> None:
        calls.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        fsync(fd)

    def recording_replace(source: str | Path, target: str | Path) -> None:
        calls.append(("replace", str(target)))
        replace(source, target)

    monkeypatch.setattr(os, "fsync", recording_fsync)
    monkeypatch.setattr(os, "replace", recording_replace)
    return calls


def test_a_commit_is_fsynced_before_its_mark_names_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Whoosh never fsyncs: a mark durable before the commit's files would, after a power cut,
    hide the commit's records from keyword search for good. Files fsynced by an earlier commit
    are not fsynced again."""
    index = KeywordIndex(tmp_path)
    index.add("state@1", 0, ["idle"], 1)
    before = set(os.listdir(tmp_path))
    calls = _fsyncs_and_replaces(monkeypatch)
    index.add("state@1", 1, ["docked"], 2)
    written = {str(tmp_path / name) for name in set(os.listdir(tmp_path)) - before}
    assert any(name.endswith(".toc") for name in written)
    assert any(name.endswith(".trm") for name in written)
    replaced = calls.index(("replace", str(tmp_path / keywords.MARKS)))
    synced = {path for kind, path in calls[:replaced] if kind == "fsync"}
    assert synced - {str(tmp_path)} == written | {
        str(tmp_path / f".{keywords.MARKS}.{os.getpid()}.tmp")
    }
    last_index_sync = max(calls.index(("fsync", path)) for path in written)
    assert calls.index(("fsync", str(tmp_path)), last_index_sync) < replaced
    index.close()


def _empty_toc(directory: Path) -> None:
    os.truncate(max(directory.glob("_MAIN_*.toc")), 0)


def _zeroed_segment(directory: Path) -> None:
    terms = max(directory.glob("*.trm"), key=lambda path: path.stat().st_mtime_ns)
    for part in directory.glob(f"{terms.stem}.*"):
        part.write_bytes(bytes(part.stat().st_size))


def _no_toc(directory: Path) -> None:
    for toc in directory.glob("_MAIN_*.toc"):
        toc.unlink()


@pytest.mark.parametrize("damage", [_empty_toc, _zeroed_segment, _no_toc])
def test_an_index_torn_by_a_power_cut_is_started_again(
    tmp_path: Path, damage: Callable[[Path], None], caplog: pytest.LogCaptureFixture
) -> None:
    """A commit cut short can leave an empty TOC, a segment of zeros, or (its TOC's rename
    lost, the old one's removal kept) none: the index is derived, so it starts empty with its
    marks at 0 rather than refusing to open or trusting marks that name what it lacks."""
    index = KeywordIndex(tmp_path)
    index.add("state@1", 0, ["idle"], 1)
    index.add("state@1", 1, ["docked"], 2)
    index.close()
    damage(tmp_path)
    reopened = KeywordIndex(tmp_path)
    assert "indexing the logs again" in caplog.text
    assert reopened.mark("state@1") == 0
    assert reopened.search(["idle"], None) == {}
    reopened.add("state@1", 0, ["idle", "docked"], 2)
    reopened.close()
    again = KeywordIndex(tmp_path)
    assert again.mark("state@1") == 2
    assert again.search(["docked"], None) == {"state@1": {1}}
    again.close()


def test_a_store_over_a_torn_keyword_index_starts_and_finds_its_records_again(
    open_store: StoreFactory,
) -> None:
    store = open_store()
    store.append([state_record(t, mode="docked") for t in range(5)], author=AUTHOR)
    store.index_keywords()
    _empty_toc(store.keywords.directory)
    store = open_store()
    store.index_keywords()
    assert store.keywords.search(["docked"], None) == {"state@1": set(range(5))}
    assert store.keywords_pending() == 0


def test_a_commit_waits_for_the_search_reading_the_segments_it_merges_away(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A searcher reads a segment's stored column only when its first hit needs it; the
    indexer's commit that merged that segment away in between (catching up after a
    restart) had removed the file, and the query was a 500 (seen in CI after kill -9). The
    commit now waits for the search, and the next search finds what it indexed. (Every
    commit merges everything here, so that this one surely removes the segments.)"""
    index = KeywordIndex(tmp_path)
    index.add("state@1", 0, ["alpha one", "beta two"], 2)
    index.add("state@1", 2, ["alpha three"], 3)
    opened = index.index.searcher
    indexing: list[threading.Thread] = []

    def searcher_while_indexing() -> whoosh.searching.Searcher:
        searcher = opened()
        if not indexing:
            indexing.append(threading.Thread(target=index.add, args=("state@1", 3, ["alpha"], 4)))
            indexing[0].start()
            indexing[0].join(timeout=2)
        return searcher

    commit = whoosh.writing.SegmentWriter.commit
    monkeypatch.setattr(
        whoosh.writing.SegmentWriter, "commit", partialmethod(commit, optimize=True)
    )
    monkeypatch.setattr(index.index, "searcher", searcher_while_indexing)
    assert index.search(["alpha"], "state@1") == {"state@1": {0, 2}}
    indexing[0].join(timeout=10)
    assert index.search(["alpha"], "state@1") == {"state@1": {0, 2, 3}}
    index.close()


TF = {
    "name": "tf",
    "fields": {
        "transforms": {
            "array": {
                "container": {
                    "child_frame_id": "string",
                    "header": {"container": {"frame_id": "string", "seq": "int"}},
                    "x": "float",
                }
            }
        },
        "names": {"array": {"array": "string"}},
        "ranges": {"array": "float"},
    },
}


def tf_record(t: int, *frames: tuple[str, str], names: list[list[str]]) -> dict[str, Any]:
    transforms = [
        {"child_frame_id": child, "header": {"frame_id": parent, "seq": t}, "x": 0.5}
        for parent, child in frames
    ]
    data = {"transforms": transforms, "names": names, "ranges": [1.0]}
    return {"template": "tf@1", "topic": "/tf", "robot": AUTHOR.signer, "t": t, "data": data}


def test_the_strings_inside_arrays_are_keywords_too(open_store: StoreFactory) -> None:
    """Only strings outside arrays were indexed: a TF message's frame ids, a joint state's
    names, a diagnostic's messages (all in arrays) were never found by keyword."""
    store = open_store()
    approve(store.catalog, TF)
    store.append(
        [
            tf_record(0, ("odom", "base_link"), names=[["wheel_left", "wheel_right"]]),
            tf_record(1, ("map", "odom"), ("base_link", "laser"), names=[]),
            tf_record(2, names=[["arm"], ["wheel_left"]]),
        ],
        author=AUTHOR,
    )
    store.index_keywords()
    assert store.keywords.search(["base_link"], None) == {"tf@1": {0, 1}}
    assert store.keywords.search(["laser"], "tf@1") == {"tf@1": {1}}
    assert store.keywords.search(["wheel_left"], None) == {"tf@1": {0, 2}}
    assert store.keywords.search(["map", "odom"], None) == {"tf@1": {1}}
    assert store.keywords_pending() == 0
    text = keyword_text(parse_template({**TF, "version": 1}))
    assert text is not None
    assert text(store.views("tf@1").docs_between(1, 2)[0]) == "odom map laser base_link"


def test_a_template_without_strings_has_no_keyword_text() -> None:
    no_strings = {"name": "n", "version": 1, "fields": {"v": {"array": {"array": "float"}}}}
    assert keyword_text(parse_template(no_strings)) is None


def test_an_index_of_older_texts_is_indexed_again(
    open_store: StoreFactory, caplog: pytest.LogCaptureFixture
) -> None:
    """Marks saved before texts held the strings inside arrays (no ``texts`` version): the
    records they name were indexed without them, so the index starts again from the logs."""
    caplog.set_level(logging.INFO, logger=keywords.__name__)
    store = open_store()
    approve(store.catalog, TF)
    store.append([tf_record(0, ("odom", "base_link"), names=[])], author=AUTHOR)
    store.append([state_record(t, mode="docked") for t in range(3)], author=AUTHOR)
    store.index_keywords()
    marks = store.keywords.directory / keywords.MARKS
    assert json.loads(marks.read_bytes()) == {"texts": 2, "marks": {"state@1": 3, "tf@1": 1}}
    marks.write_text(json.dumps({"state@1": 3, "tf@1": 1}))
    store = open_store()
    assert "holds texts of version 1, not 2; indexing the logs again" in caplog.text
    assert store.keywords_pending() == 4
    store.index_keywords()
    assert store.keywords.search(["base_link"], None) == {"tf@1": {0}}
    assert store.keywords.search(["docked"], None) == {"state@1": {0, 1, 2}}
