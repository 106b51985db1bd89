"""Queries over the record views: filters, comparisons, keywords, pages; and state intervals.

A query names at most one template (comparisons need one: a field path means something only
in its template), a topic, a robot, a time window ``[start, end)`` in nanoseconds, any number
of comparisons ``field op value`` (``= != < <= > >=``, combined with AND) and keywords. Per
sealed segment the time window and the comparisons on indexed fields (int, float, bool) are
binary searches in the segment's sorted indexes, and a segment whose value ranges cannot
match is skipped without being opened; only what the indexes cannot decide (topic, robot,
strings, ``!=``) reads the segment's documents. The records themselves are read from the log,
exactly as they were acknowledged.

Results come in log order (template id, then index); a page ends after ``limit`` records or
after ``MAX_SCANNED`` documents examined, and ``next`` is the cursor to continue from, so
that no query costs more than a bounded amount of work however unselective it is.
"""

from __future__ import annotations

import math
import re
from array import array
from bisect import bisect_left, bisect_right
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from robocloud import bounded_json
from robocloud.cid import CIDError, parse_cid
from robocloud.storage import Interval
from robocloud.templates import TEMPLATE_ID, Container, Scalar, Template
from services.storage.keywords import KeywordIndex
from services.storage.recordstore import RecordStore, StoredRecord
from services.storage.segments import INDEXED_KINDS, Doc, SealedSegment, TemplateSegments

MAX_LIMIT = 1000
MAX_WHERE = 16
MAX_SCANNED = 1_000_000
"""Documents one page may examine before it answers with a cursor."""
MAX_INTERVAL_SCAN = 2_000_000
"""Documents one intervals answer may examine, whatever their robot, before it is refused."""
WHERE = re.compile(r"([a-z][a-z0-9_.]{0,639})\s*(==|!=|<=|>=|=|<|>)(.*)", re.DOTALL)
ORDERING = frozenset(("<", "<=", ">", ">="))
TEXT_KINDS = frozenset(("string", "image", "file"))
"""Kinds whose values are text, and so may be quoted in a comparison."""
CURSOR = re.compile(r"([a-z][a-z0-9_]{0,62}@[1-9][0-9]{0,8})/(0|[1-9][0-9]{0,18})")


class QueryInvalid(Exception):
    """A query parameter that cannot be used; ``parameter`` names it (``where[1]``)."""

    def __init__(self, parameter: str, message: str, code: str = "invalid_query") -> None:
        super().__init__(f"{parameter}: {message}")
        self.parameter = parameter
        self.code = code


@dataclass(frozen=True)
class Comparison:
    """``field op value`` with the value parsed for the field's type."""

    field: str
    op: str
    value: Any
    indexed: bool

    def matches(self, actual: Any) -> bool:
        if self.op == "=":
            return bool(actual == self.value)
        if self.op == "!=":
            return bool(actual != self.value)
        if self.op == "<":
            return bool(actual < self.value)
        if self.op == "<=":
            return bool(actual <= self.value)
        if self.op == ">":
            return bool(actual > self.value)
        return bool(actual >= self.value)


@dataclass(frozen=True)
class RecordQuery:
    template: str | None = None
    topic: str | None = None
    robot: str | None = None
    start: int | None = None
    end: int | None = None
    where: tuple[str, ...] = ()
    keywords: str | None = None
    limit: int = 100
    cursor: str | None = None


@dataclass
class Page:
    records: list[StoredRecord]
    next: str | None
    keywords_pending: int


def _value(kind: str, text: str, parameter: str) -> Any:
    """``text`` as a value of ``kind``; QueryInvalid naming the parameter otherwise."""
    try:
        if kind == "int":
            if not re.fullmatch(r"-?[0-9]{1,16}", text):
                raise ValueError(text)
            return int(text)
        if kind == "float":
            number = float(text)
            if not math.isfinite(number) or len(text) > 64:
                raise ValueError(text)
            return number
        if kind == "bool":
            if text not in ("true", "false"):
                raise ValueError(text)
            return text == "true"
        if kind in ("image", "file"):
            parse_cid(text, parameter)
        return text
    except (ValueError, CIDError) as exc:
        raise QueryInvalid(parameter, f"{text[:80]!r} is not a {kind} value") from exc


def parse_comparison(template: Template, text: str, parameter: str) -> Comparison:
    """One ``field op value`` against ``template``.

    Whitespace around the operator and the value is not part of them (``speed > 2``). A
    value in double quotes is a JSON string, kept exactly: ``mode=" docked "`` holds its
    spaces, ``mode="=x"`` its ``=``; quotes are for text fields (string, image, file).
    """
    match = WHERE.fullmatch(text)
    if match is None:
        raise QueryInvalid(
            parameter,
            f"{text[:80]!r} is not field op value (op one of = != < <= > >=)",
            code="invalid_operator",
        )
    path, op, raw = match.group(1), match.group(2), match.group(3).strip()
    op = "=" if op == "==" else op
    if raw.startswith('"'):
        return build_comparison(template, path, op, _quoted(raw, parameter), parameter, quoted=True)
    if raw[:1] in ("=", "<", ">", "!"):
        raise QueryInvalid(parameter, f"malformed operator in {text[:80]!r}", "invalid_operator")
    return build_comparison(template, path, op, raw, parameter)


def build_comparison(
    template: Template,
    path: str,
    op: str,
    value_text: str,
    parameter: str,
    *,
    value_parameter: str | None = None,
    quoted: bool = False,
) -> Comparison:
    """``path op value`` against ``template`` from its parts, none of them read as syntax:
    a path must be a scalar leaf of the template, the value is parsed for its type as it is.

    ``parameter`` names the query parameter of the path (and of the value, unless
    ``value_parameter`` names another): ``GET /v1/intervals`` gives field and value apart.
    """
    kind = template.field_at(path)
    if kind is None:
        raise QueryInvalid(
            parameter, f"{template.id} has no field {path[:80]}", code="unknown_field"
        )
    if isinstance(kind, Container):
        raise QueryInvalid(parameter, _not_a_value(path, kind), code="unknown_field")
    if not isinstance(kind, Scalar) or kind.kind.startswith("range"):
        raise QueryInvalid(parameter, f"{path} is not a scalar field", code="unknown_field")
    if op in ORDERING and kind.kind not in ("int", "float"):
        raise QueryInvalid(
            parameter, f"{op} compares numbers; {path} is {kind.kind}", code="invalid_operator"
        )
    value_parameter = value_parameter or parameter
    if quoted and kind.kind not in TEXT_KINDS:
        raise QueryInvalid(value_parameter, f"a quoted value is text; {path} is {kind.kind}")
    value = _value(kind.kind, value_text, value_parameter)
    indexed = kind.kind in INDEXED_KINDS and op != "!="
    return Comparison(path, op, value, indexed)


def _not_a_value(path: str, group: Container) -> str:
    """Why ``path`` cannot be compared, and which paths under it can."""
    names = list(group.fields)
    if not names:
        return f"{path} is an empty group of fields, not a value"
    listed = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "")
    return (
        f"{path} is a group of fields ({listed}), not a value:"
        f" compare one of them, like {path}.{names[0]}"
    )


def _quoted(raw: str, parameter: str) -> str:
    """The text of a JSON string literal, which must be all of ``raw``."""
    try:
        value = bounded_json.loads(raw)
    except bounded_json.JsonError as exc:
        raise QueryInvalid(parameter, f"{raw[:80]!r} is not one quoted JSON string") from exc
    if not isinstance(value, str):
        raise QueryInvalid(parameter, f"{raw[:80]!r} is not one quoted JSON string")
    return value


def parse_cursor(text: str) -> tuple[str, int]:
    match = CURSOR.fullmatch(text)
    if match is None:
        raise QueryInvalid("cursor", f"{text[:80]!r} is not a cursor from a previous page")
    return match.group(1), int(match.group(2))


@dataclass
class _Scan:
    """What one page collected so far and how much it examined."""

    limit: int
    found: list[tuple[str, int]] = field(default_factory=list)
    scanned: int = 0
    stopped_at: tuple[str, int] | None = None

    @property
    def full(self) -> bool:
        return len(self.found) > self.limit or self.stopped_at is not None


@dataclass(frozen=True)
class _KeywordHits:
    """One template's keyword hits, sorted once per query: each segment takes its own by
    bisection, where walking every hit for every segment cost hits times segments."""

    indexes: list[int]

    @classmethod
    def of(cls, hits: dict[str, set[int]], template_id: str) -> _KeywordHits:
        return cls(sorted(hits.get(template_id, ())))

    def between(self, start: int, stop: int) -> list[int]:
        """The hits in ``[start, stop)``."""
        return self.indexes[bisect_left(self.indexes, start) : bisect_left(self.indexes, stop)]

    def __contains__(self, index: int) -> bool:
        found = bisect_left(self.indexes, index)
        return found < len(self.indexes) and self.indexes[found] == index


def _bounds(comparison: Comparison) -> tuple[float | None, float | None, bool, bool]:
    value = float(comparison.value)
    return {
        "=": (value, value, False, False),
        "<": (None, value, False, True),
        "<=": (None, value, False, False),
        ">": (value, None, True, False),
        ">=": (value, None, False, False),
    }[comparison.op]


def _range_excludes(comparison: Comparison, low: float, high: float) -> bool:
    """Whether no value in ``[low, high]`` can satisfy an indexed comparison."""
    floor, ceiling, floor_open, ceiling_open = _bounds(comparison)
    if floor is not None and (high < floor or (floor_open and high <= floor)):
        return True
    return ceiling is not None and (low > ceiling or (ceiling_open and low >= ceiling))


class QueryEngine:
    """Answers queries from a :class:`RecordStore`'s views."""

    def __init__(self, store: RecordStore) -> None:
        self.store = store

    @property
    def keywords(self) -> KeywordIndex:
        return self.store.keywords

    def _template(self, template_id: str) -> TemplateSegments | None:
        if not TEMPLATE_ID.fullmatch(template_id):
            raise QueryInvalid("template", f"{template_id[:80]!r} is not a template id")
        return self.store.views(template_id)

    def records(self, query: RecordQuery) -> Page:
        if not 1 <= query.limit <= MAX_LIMIT:
            raise QueryInvalid("limit", f"must be from 1 to {MAX_LIMIT}")
        if len(query.where) > MAX_WHERE:
            raise QueryInvalid("where", f"at most {MAX_WHERE} comparisons")
        if query.where and query.template is None:
            raise QueryInvalid("where", "comparisons need a template")
        _check_window(query.start, query.end)
        after = parse_cursor(query.cursor) if query.cursor is not None else None
        if query.template is not None:
            views = self._template(query.template)
            if views is None:
                self._check_known(query.template)
            chosen = [views] if views is not None else []
        else:
            chosen = [v for t in self.store.template_ids() if (v := self.store.views(t))]
        comparisons: dict[str, list[Comparison]] = {}
        for views in chosen:
            comparisons[views.template.id] = [
                parse_comparison(views.template, text, f"where[{n}]")
                for n, text in enumerate(query.where)
            ]
        hits: dict[str, set[int]] | None = None
        if query.keywords is not None:
            words = self.keywords.terms(query.keywords)
            if not words:
                raise QueryInvalid("keywords", "holds no word")
            hits = self.keywords.search(words, query.template)
        scan = _Scan(query.limit)
        for views in chosen:
            template_id = views.template.id
            if after is not None and template_id < after[0]:
                continue
            skip = after[1] if after is not None and template_id == after[0] else -1
            keyword_hits = _KeywordHits.of(hits, template_id) if hits is not None else None
            if keyword_hits is not None and not keyword_hits.indexes:
                continue
            self._scan(views, query, comparisons[template_id], keyword_hits, skip, scan)
            if scan.full:
                break
        found = scan.found[: query.limit]
        next_cursor = None
        if len(scan.found) > query.limit:
            next_cursor = "{}/{}".format(*found[-1])
        elif scan.stopped_at is not None:
            next_cursor = "{}/{}".format(*scan.stopped_at)
        records: list[StoredRecord] = []
        for template_id, index in found:
            records.extend(self.store.read(template_id, [index]))
        return Page(records, next_cursor, self.store.keywords_pending())

    def _check_known(self, template_id: str) -> None:
        """A template with no records yet answers an empty page; an unknown one is 404."""
        self.store.catalog.get(template_id)

    def _doc_filter(
        self, query: RecordQuery, comparisons: list[Comparison], *, indexed_done: bool
    ) -> Callable[[Doc], bool] | None:
        checks: list[Callable[[Doc], bool]] = []
        if query.topic is not None:
            topic = query.topic
            checks.append(lambda doc: doc["_topic"] == topic)
        if query.robot is not None:
            robot = query.robot
            checks.append(lambda doc: doc["_robot"] == robot)
        if not indexed_done:
            start, end = query.start, query.end
            if start is not None:
                checks.append(lambda doc: doc["_t"] >= start)
            if end is not None:
                checks.append(lambda doc: doc["_t"] < end)
        for comparison in comparisons:
            if indexed_done and comparison.indexed:
                continue
            checks.append(
                lambda doc, c=comparison: c.matches(doc[c.field])  # type: ignore[misc]
            )
        if not checks:
            return None
        return lambda doc: all(check(doc) for check in checks)

    def _scan(
        self,
        views: TemplateSegments,
        query: RecordQuery,
        comparisons: list[Comparison],
        keyword_hits: _KeywordHits | None,
        skip: int,
        scan: _Scan,
    ) -> None:
        template_id = views.template.id
        sealed, tail = views.snapshot()
        indexed = [c for c in comparisons if c.indexed]
        segment_filter = self._doc_filter(query, comparisons, indexed_done=True)
        for segment in sealed:
            if segment.first + segment.count - 1 <= skip or self._pruned(segment, query, indexed):
                continue
            candidates = self._candidates(views, segment, query, indexed, keyword_hits)
            positions = _after(candidates, skip - segment.first)
            if not positions:
                continue
            docs = views.docs(segment) if segment_filter is not None else None
            for position in positions:
                index = segment.first + position
                scan.scanned += 1
                if docs is None or segment_filter is None or segment_filter(docs[position]):
                    scan.found.append((template_id, index))
                    if scan.full:
                        return
                if scan.scanned >= MAX_SCANNED:
                    scan.stopped_at = (template_id, index)
                    return
        tail_filter = self._doc_filter(query, comparisons, indexed_done=False)
        for doc in tail:
            index = doc["_i"]
            if index <= skip or (keyword_hits is not None and index not in keyword_hits):
                continue
            scan.scanned += 1
            if tail_filter is None or tail_filter(doc):
                scan.found.append((template_id, index))
                if scan.full:
                    return

    def _pruned(
        self, segment: SealedSegment, query: RecordQuery, indexed: list[Comparison]
    ) -> bool:
        low, high = segment.ranges["_t"]
        if query.start is not None and high < query.start:
            return True
        if query.end is not None and low >= query.end:
            return True
        for comparison in indexed:
            field_low, field_high = segment.ranges[comparison.field]
            if _range_excludes(comparison, field_low, field_high):
                return True
        return False

    def _candidates(
        self,
        views: TemplateSegments,
        segment: SealedSegment,
        query: RecordQuery,
        indexed: list[Comparison],
        keyword_hits: _KeywordHits | None,
    ) -> Sequence[int]:
        """Positions in the segment the indexes allow, in order."""
        sets: list[array[int]] = []
        if query.start is not None or query.end is not None:
            sets.append(views.index(segment, "_t").between(query.start, query.end, high_open=True))
        for comparison in indexed:
            low, high, low_open, high_open = _bounds(comparison)
            index = views.index(segment, comparison.field)
            sets.append(index.between(low, high, low_open=low_open, high_open=high_open))
        if keyword_hits is not None:
            inside = keyword_hits.between(segment.first, segment.first + segment.count)
            sets.append(array("I", (i - segment.first for i in inside)))
        if not sets:
            return range(segment.count)
        sets.sort(key=len)
        chosen = set(sets[0])
        for other in sets[1:]:
            chosen.intersection_update(other)
            if not chosen:
                break
        return sorted(chosen)

    def intervals(
        self,
        template_id: str,
        field_path: str,
        value_text: str,
        *,
        robot: str | None = None,
        start: int | None = None,
        end: int | None = None,
    ) -> list[Interval]:
        """Per robot, when ``field == value`` began (enter) and stopped (exit, None: still).

        ``field_path`` is a leaf of the template and ``value_text`` its value exactly, never
        parsed as ``where`` syntax: the condition was once the text ``f"{field}={value}"``,
        so a field ``i<`` asked ``i <= value`` and a value ``=s3`` matched ``s3``.
        """
        _check_window(start, end)
        views = self._template(template_id)
        template = (
            views.template if views is not None else self.store.catalog.get(template_id).template
        )
        state = build_comparison(
            template, field_path, "=", value_text, "field", value_parameter="value"
        )
        if views is None:
            return []
        query = RecordQuery(template=template_id, robot=robot, start=start, end=end)
        by_robot: dict[str, list[tuple[int, int, bool]]] = {}
        for doc in self._window_docs(views, query):
            by_robot.setdefault(doc["_robot"], []).append(
                (doc["_t"], doc["_i"], state.matches(doc[state.field]))
            )
        intervals = []
        for name in sorted(by_robot):
            entered: int | None = None
            for t, _, inside in sorted(by_robot[name]):
                if inside and entered is None:
                    entered = t
                elif not inside and entered is not None:
                    intervals.append(Interval(name, entered, t))
                    entered = None
            if entered is not None:
                intervals.append(Interval(name, entered, None))
        return intervals

    def _window_docs(self, views: TemplateSegments, query: RecordQuery) -> Iterator[Doc]:
        """The documents in ``query``'s window of its robot (if it names one), in log order.

        ``MAX_INTERVAL_SCAN`` counts every document examined, kept or not: no index knows the
        robots, so a robot with few records (or none) in a broad window costs as much as all
        of them, and it is refused as too broad as they are. Counting only the kept ones let
        a robot without records decode every segment with no bound.
        """
        keep = self._doc_filter(query, [], indexed_done=False)
        for examined, doc in enumerate(self._in_window(views, query), start=1):
            if examined > MAX_INTERVAL_SCAN:
                raise QueryInvalid(
                    "start",
                    f"more than {MAX_INTERVAL_SCAN} records in the window, of any robot; "
                    "narrow the time window",
                    code="query_too_broad",
                )
            if keep is None or keep(doc):
                yield doc

    def _in_window(self, views: TemplateSegments, query: RecordQuery) -> Iterator[Doc]:
        """The sealed documents the time index leaves in ``query``'s window, then the tail's
        (which has no index); a segment the index leaves empty is not decoded."""
        sealed, tail = views.snapshot()
        for segment in sealed:
            if self._pruned(segment, query, []):
                continue
            positions = self._candidates(views, segment, query, [], None)
            if positions:
                docs = views.docs(segment)
                yield from (docs[position] for position in positions)
        yield from tail


def _after(positions: Sequence[int], skip: int) -> Sequence[int]:
    """The sorted ``positions`` past ``skip`` (a cursor's position in the segment, negative
    for none): a segment left with none is never decoded, which costs more than its indexes."""
    return positions[bisect_right(positions, skip) :]


def _check_window(start: int | None, end: int | None) -> None:
    """Records and intervals refuse the same inverted window (intervals answered it empty)."""
    if start is not None and end is not None and start > end:
        raise QueryInvalid("start", "is after end")
