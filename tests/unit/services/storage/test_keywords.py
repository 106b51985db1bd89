"""The keyword index: one document per distinct text of a batch, its records as runs."""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.storage import keywords
from services.storage.keywords import KeywordIndex, TooManyKeywordHits, parse_runs, runs


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


def test_a_query_matching_too_many_records_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(keywords, "MAX_HITS", 10)
    index = KeywordIndex(tmp_path)
    index.add("state@1", 0, ["idle"] * 11, 11)
    with pytest.raises(TooManyKeywordHits, match="more than 10 records"):
        index.search(["idle"], None)
    index.close()
