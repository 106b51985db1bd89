"""Queries: filters through the sealed segments' indexes and the tail, pages, intervals."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from services.storage import queries
from services.storage.catalog import TemplateNotFound
from services.storage.queries import QueryEngine, QueryInvalid, RecordQuery
from services.storage.recordstore import RecordStore
from services.storage.segments import Doc, SealedSegment, TemplateSegments
from tests.unit.services.storage.conftest import (
    AUTHOR,
    REVIEWER,
    ROBOT_A,
    ROBOT_B,
    StoreFactory,
    state_record,
)


def _filled(open_store: StoreFactory) -> RecordStore:
    """100 records (t = 0..99, two robots alternating): 6 sealed segments and a tail of 4."""
    store = open_store()
    modes = ["idle"] * 10 + ["docked"] * 5 + ["moving"] * 85
    records = [
        state_record(t, robot=ROBOT_A if t % 2 == 0 else ROBOT_B, mode=modes[t]) for t in range(100)
    ]
    store.append(records[:50], author=AUTHOR)
    store.append(records[50:], author=AUTHOR)
    return store


def _ts(store: RecordStore, **filters: Any) -> list[int]:
    page = QueryEngine(store).records(RecordQuery(template="state@1", limit=1000, **filters))
    return [stored.record["t"] for stored in page.records]


def test_filters_combine_with_and(open_store: StoreFactory) -> None:
    store = _filled(open_store)
    assert _ts(store, start=20, end=25) == [20, 21, 22, 23, 24]
    assert _ts(store, start=95) == [95, 96, 97, 98, 99]
    assert _ts(store, start=30, end=40, robot=ROBOT_B) == [31, 33, 35, 37, 39]
    assert _ts(store, where=("speed>=9.5",)) == [95, 96, 97, 98, 99]
    assert _ts(store, where=("speed>9.5", "count!=0")) == [96, 97, 99]
    assert _ts(store, where=("pose.x<3",)) == [0, 1, 2]
    assert _ts(store, where=("pose.x<=3", "pose.x>1")) == [2, 3]
    assert _ts(store, where=("mode=docked",)) == [10, 11, 12, 13, 14]
    assert _ts(store, where=("docked==true", "count = 5")) == [12]
    assert _ts(store, where=("mode!=moving", "count>=5")) == [5, 6, 12, 13]
    assert _ts(store, topic="/other") == []
    assert _ts(store, start=10, end=10) == []


def test_pages_follow_the_cursor(open_store: StoreFactory) -> None:
    store = _filled(open_store)
    engine = QueryEngine(store)
    seen: list[int] = []
    cursor = None
    while True:
        page = engine.records(
            RecordQuery(template="state@1", where=("count<3",), limit=7, cursor=cursor)
        )
        seen.extend(stored.record["t"] for stored in page.records)
        if page.next is None:
            break
        cursor = page.next
    assert seen == [t for t in range(100) if t % 7 < 3]
    everything = engine.records(RecordQuery(limit=1000))
    assert len(everything.records) == 100
    assert everything.next is None


def test_keywords_find_records_once_indexed(open_store: StoreFactory) -> None:
    store = _filled(open_store)
    store.index_keywords()
    engine = QueryEngine(store)
    page = engine.records(RecordQuery(keywords="DOCKED", limit=100))
    assert [stored.id for stored in page.records] == [f"state-1-{t}" for t in range(10, 15)]
    assert page.keywords_pending == 0
    page = engine.records(RecordQuery(template="state@1", keywords="docked", robot=ROBOT_A))
    assert [stored.record["t"] for stored in page.records] == [10, 12, 14]
    with pytest.raises(QueryInvalid) as empty:
        engine.records(RecordQuery(keywords="  ,; "))
    assert empty.value.parameter == "keywords"


class WalkedHits(set[int]):
    """Keyword hits that count the indexes walked over them."""

    walked = 0

    def __iter__(self) -> Iterator[int]:
        for index in super().__iter__():
            WalkedHits.walked += 1
            yield index


def test_keyword_hits_are_walked_once_per_query_not_once_per_segment(
    open_store: StoreFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each segment walked every hit of its template to find its own, hits times segments;
    the hits are sorted once and each segment (and the tail) finds its own by bisection."""
    store = _filled(open_store)
    store.index_keywords()
    search = store.keywords.search

    def walked_hits(words: list[str], template_id: str | None) -> dict[str, set[int]]:
        return {name: WalkedHits(hits) for name, hits in search(words, template_id).items()}

    monkeypatch.setattr(store.keywords, "search", walked_hits)
    monkeypatch.setattr(WalkedHits, "walked", 0)
    page = QueryEngine(store).records(RecordQuery(keywords="moving", robot=ROBOT_B))
    assert [stored.record["t"] for stored in page.records] == list(range(15, 100, 2))
    assert WalkedHits.walked == 85


def segments_read(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The first index of each sealed segment whose documents a query asks for, in order."""
    read: list[int] = []
    docs = TemplateSegments.docs

    def counted(views: TemplateSegments, segment: SealedSegment) -> list[Doc]:
        read.append(segment.first)
        return docs(views, segment)

    monkeypatch.setattr(TemplateSegments, "docs", counted)
    return read


@pytest.mark.parametrize(
    ("query", "found"),
    [
        (RecordQuery(template="state@1", keywords="docked", robot=ROBOT_A), [10, 12, 14]),
        (RecordQuery(template="state@1", where=("count=3", "pose.x<=2"), robot=ROBOT_A), []),
        (
            RecordQuery(template="state@1", keywords="docked", robot=ROBOT_A, cursor="state@1/14"),
            [],
        ),
    ],
)
def test_a_segment_left_without_candidates_is_never_decoded(
    open_store: StoreFactory,
    monkeypatch: pytest.MonkeyPatch,
    query: RecordQuery,
    found: list[int],
) -> None:
    """A segment's documents were decoded for the robot filter before the indexes (keywords,
    comparisons, the cursor) said whether any of its positions was left: a query whose
    keywords hit one segment decoded all six."""
    store = _filled(open_store)
    store.index_keywords()
    read = segments_read(monkeypatch)
    page = QueryEngine(store).records(query)
    assert [stored.record["t"] for stored in page.records] == found
    assert read == ([0] if found else [])


@pytest.mark.parametrize(
    ("where", "message"),
    [
        ("nowhere=1", "state@1 has no field nowhere"),
        ("pose.x.y=1", "state@1 has no field pose.x.y"),
        (
            "pose=1",
            "pose is a group of fields (x, y), not a value: compare one of them, like pose.x",
        ),
        ("ranges=1", "ranges is not a scalar field"),
    ],
)
def test_a_field_that_is_not_a_value_says_what_it_is(
    open_store: StoreFactory, where: str, message: str
) -> None:
    """A group of fields was "state@1 has no field pose": it has, and the message now names
    the values under it that a comparison may name."""
    store = _filled(open_store)
    with pytest.raises(QueryInvalid) as invalid:
        QueryEngine(store).records(RecordQuery(template="state@1", where=(where,)))
    assert (invalid.value.code, str(invalid.value)) == ("unknown_field", f"where[0]: {message}")


@pytest.mark.parametrize(
    ("where", "code"),
    [
        ("nowhere=1", "unknown_field"),
        ("pose=1", "unknown_field"),
        ("ranges=1", "unknown_field"),
        ("speed~1", "invalid_operator"),
        ("speed=>1", "invalid_operator"),
        ("speed<<1", "invalid_operator"),
        ("speed", "invalid_operator"),
        ("mode<x", "invalid_operator"),
        ("speed>fast", "invalid_query"),
        ("speed>nan", "invalid_query"),
        ("count>1.5", "invalid_query"),
        ("docked=1", "invalid_query"),
        ("Speed>1", "invalid_operator"),
    ],
)
def test_bad_comparisons_are_named(open_store: StoreFactory, where: str, code: str) -> None:
    store = _filled(open_store)
    with pytest.raises(QueryInvalid) as invalid:
        QueryEngine(store).records(RecordQuery(template="state@1", where=("count>0", where)))
    assert (invalid.value.parameter, invalid.value.code) == ("where[1]", code)


def test_bad_query_parameters(open_store: StoreFactory) -> None:
    engine = QueryEngine(_filled(open_store))
    for query, parameter in [
        (RecordQuery(where=("count>1",)), "where"),
        (RecordQuery(limit=0), "limit"),
        (RecordQuery(limit=1001), "limit"),
        (RecordQuery(cursor="state@1"), "cursor"),
        (RecordQuery(template="State"), "template"),
        (RecordQuery(start=5, end=4), "start"),
        (RecordQuery(template="state@1", where=("count>1",) * 17), "where"),
    ]:
        with pytest.raises(QueryInvalid) as invalid:
            engine.records(query)
        assert invalid.value.parameter == parameter
    with pytest.raises(TemplateNotFound):
        engine.records(RecordQuery(template="gps@1"))


def test_intervals_per_robot(open_store: StoreFactory) -> None:
    store = open_store()
    modes = ["idle", "docked", "docked", "idle", "docked"]
    records = [state_record(t * 10, mode=mode) for t, mode in enumerate(modes)]
    records += [state_record(t * 10 + 5, robot=ROBOT_B, mode="docked") for t in range(3)]
    store.append(records, author=AUTHOR)
    engine = QueryEngine(store)
    found = engine.intervals("state@1", "mode", "docked")
    assert [(i.robot, i.enter, i.exit) for i in found] == [
        (ROBOT_A, 10, 30),
        (ROBOT_A, 40, None),
        (ROBOT_B, 5, None),
    ]
    within = engine.intervals("state@1", "docked", "true", robot=ROBOT_A, start=0, end=35)
    assert [(i.enter, i.exit) for i in within] == [(10, 30)]
    with pytest.raises(QueryInvalid) as invalid:
        engine.intervals("state@1", "gear", "1")
    assert invalid.value.code == "unknown_field"
    with pytest.raises(QueryInvalid) as inverted:  # answered [] while records refused it
        engine.intervals("state@1", "mode", "docked", start=40, end=10)
    assert (inverted.value.parameter, str(inverted.value)) == ("start", "start: is after end")


def test_the_interval_bound_counts_every_record_examined_whatever_its_robot(
    open_store: StoreFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The bound counted only the asked robot's records, so a robot that wrote none had every
    segment of the window decoded, with no bound at all."""
    store = _filled(open_store)
    monkeypatch.setattr(queries, "MAX_INTERVAL_SCAN", 50)
    engine = QueryEngine(store)
    for robot in (REVIEWER, ROBOT_A):  # REVIEWER wrote no record; ROBOT_A wrote 50 of 100
        with pytest.raises(QueryInvalid) as broad:
            engine.intervals("state@1", "mode", "docked", robot=robot)
        assert (broad.value.parameter, broad.value.code) == ("start", "query_too_broad")
    # 32 records in the window and the tail's 4 are examined: within the bound.
    assert engine.intervals("state@1", "mode", "docked", robot=REVIEWER, end=32) == []
    narrow = engine.intervals("state@1", "mode", "docked", robot=ROBOT_A, end=32)
    assert [(i.robot, i.enter, i.exit) for i in narrow] == [(ROBOT_A, 10, 16)]


def test_interval_field_and_value_are_never_read_as_where_syntax(
    open_store: StoreFactory,
) -> None:
    """The condition was the text f"{field}={value}": a field "count<" asked count <= 0, and
    a value "=docked" matched "docked"."""
    store = open_store()
    modes = ["docked", " docked ", "=docked", "idle"]
    store.append([state_record(t, mode=mode) for t, mode in enumerate(modes)], author=AUTHOR)
    engine = QueryEngine(store)

    def spans(field: str, value: str) -> list[tuple[int, int | None]]:
        return [(i.enter, i.exit) for i in engine.intervals("state@1", field, value)]

    assert spans("mode", "docked") == [(0, 1)]
    assert spans("mode", " docked ") == [(1, 2)]
    assert spans("mode", "=docked") == [(2, 3)]
    for field in ("count<", "count<=", "mode!", "pose", "", "mode=docked"):
        with pytest.raises(QueryInvalid) as unknown:
            engine.intervals("state@1", field, "0")
        assert (unknown.value.parameter, unknown.value.code) == ("field", "unknown_field")
    with pytest.raises(QueryInvalid) as bad_value:
        engine.intervals("state@1", "count", "<1")
    assert (bad_value.value.parameter, bad_value.value.code) == ("value", "invalid_query")


def test_a_field_is_checked_before_its_template_has_records(open_store: StoreFactory) -> None:
    engine = QueryEngine(open_store())
    assert engine.intervals("state@1", "mode", "docked") == []
    with pytest.raises(QueryInvalid) as unknown:
        engine.intervals("state@1", "gear", "1")
    assert unknown.value.code == "unknown_field"


def test_a_quoted_where_value_keeps_its_whitespace(open_store: StoreFactory) -> None:
    store = open_store()
    modes = ["docked", " docked ", "=docked", 'say "hi"']
    store.append([state_record(t, mode=mode) for t, mode in enumerate(modes)], author=AUTHOR)
    assert _ts(store, where=("mode = docked ",)) == [0]
    assert _ts(store, where=('mode=" docked "',)) == [1]
    assert _ts(store, where=('mode = "=docked"',)) == [2]
    assert _ts(store, where=('mode="say \\"hi\\""',)) == [3]
    assert _ts(store, where=('mode!="docked"',)) == [1, 2, 3]
    for where in ('mode="open', 'mode="a"b', 'count="1"', 'mode="\\ud800"'):
        with pytest.raises(QueryInvalid) as invalid:
            _ts(store, where=(where,))
        assert (invalid.value.parameter, invalid.value.code) == ("where[0]", "invalid_query")
