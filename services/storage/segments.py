"""TinyDB segments of one template's records, with our own time and numeric indexes.

TinyDB rewrites its whole file on every insert, so it is never written one record at a time:
records gather in an in-memory tail (rebuilt from the record log at start) and, once
``segment_records`` of them are there, the tail is written as a new TinyDB database in one
call of its storage (the file TinyDB's ``insert_multiple`` would write into a fresh database,
without the copy of every document it makes first) and sealed: never written again. Beside
each sealed segment lie its indexes, sorted arrays of (value, position) for ``t`` and for
every int, float and bool leaf outside arrays, so that a time window or a comparison is two
binary searches per segment instead of a scan. ``segments.json`` lists the sealed segments
with their value ranges; it is replaced atomically after a segment's files are on disk, so it
is the views' durable mark: a file it does not list is a leftover of a crash and is removed at
open.

A TinyDB document is a record flattened: envelope keys prefixed with ``_`` (``_i`` its index
in the template's log, ``_t``, ``_topic``, ``_robot``) and each leaf under its dotted path
(``pose.position.x``); field names cannot start with ``_``, so the two never collide.
"""

from __future__ import annotations

import bisect
import json
import os
import struct
import threading
from array import array
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from operator import itemgetter
from pathlib import Path
from typing import Any

import numpy as np
import orjson
from tinydb import TinyDB
from tinydb.storages import Storage

from robocloud.templates import ArrayOf, Container, FieldType, Scalar, Template
from services.common.durable import atomic_write, fsync_dir, write_synced

Doc = dict[str, Any]
TABLE = "records"
MANIFEST = "segments.json"
INDEXED_KINDS = frozenset(("int", "float", "bool"))
ENVELOPE = {"t": "_t", "topic": "_topic", "robot": "_robot"}


class SegmentStorage(Storage):
    """TinyDB's storage for segment files: the JSON document ``JSONStorage`` keeps, through
    orjson, since a segment is written whole once and read whole by queries (several times
    faster than the standard library both ways). Records hold no NaN and no integer beyond
    64 bits, which orjson would refuse."""

    def __init__(self, path: str | Path, access_mode: str = "r+") -> None:
        self.path = Path(path)
        self.writable = access_mode != "r"

    def read(self) -> dict[str, dict[str, Any]] | None:
        try:
            text = self.path.read_bytes()
        except FileNotFoundError:
            return None
        return orjson.loads(text) if text else None

    def write(self, data: dict[str, dict[str, Any]]) -> None:
        if not self.writable:
            raise OSError(f"{self.path} is opened read-only")
        self.path.write_bytes(orjson.dumps(data))

    def close(self) -> None:
        """Nothing stays open between a read and a write."""


def flattener(template: Template) -> Callable[[dict[str, Any], int], Doc]:
    """The TinyDB document of a record of ``template`` and its index.

    Generated as one dict display per template, as rosbags generates its deserializers: every
    record committed passes through it, and a walk over the leaves costs three times as much.
    Field names enter the source through ``repr`` only."""
    reads = ", ".join(
        f"{path!r}: data" + "".join(f"[{key!r}]" for key in path.split("."))
        for path, _ in template.leaves()
    )
    source = (
        "def flatten(record, index):\n"
        "    data = record['data']\n"
        "    return {'_i': index, '_t': record['t'], '_topic': record['topic'], "
        f"'_robot': record['robot'], {reads}}}\n"
    )
    namespace: dict[str, Any] = {}
    exec(compile(source, f"<flattener of {template.id}>", "exec"), namespace)
    flatten: Callable[[dict[str, Any], int], Doc] = namespace["flatten"]
    return flatten


STRING = Scalar("string")


def keyword_text(template: Template) -> Callable[[Doc], str] | None:
    """What the keyword index reads of a document: its strings, space-separated (None for a
    template without one). Strings inside arrays count too: a TF message's frame ids, a
    joint state's names, a diagnostic's status messages are all in arrays."""
    plain = [path for path, kind in template.leaves() if kind == STRING]
    nested = [
        (path, strings)
        for path, kind in template.leaves()
        if isinstance(kind, ArrayOf) and (strings := _strings_of(kind)) is not None
    ]
    if not nested:
        if not plain:
            return None
        if len(plain) == 1:
            return itemgetter(plain[0])
        read = itemgetter(*plain)
        return lambda doc: " ".join(read(doc))

    def text(doc: Doc) -> str:
        words = [doc[path] for path in plain]
        for path, strings in nested:
            words.extend(strings(doc[path]))
        return " ".join(words)

    return text


def _strings_of(kind: FieldType) -> Callable[[Any], Iterator[str]] | None:
    """The strings of a value of ``kind``, in order (None when it can hold none)."""
    if kind == STRING:
        return lambda value: iter((value,))
    if isinstance(kind, ArrayOf):
        item = _strings_of(kind.item)
        if item is None:
            return None
        return lambda values: (string for value in values for string in item(value))
    if isinstance(kind, Container):
        fields = [
            (name, strings)
            for name, inner in kind.fields.items()
            if (strings := _strings_of(inner))
        ]
        if not fields:
            return None
        return lambda value: (string for name, strings in fields for string in strings(value[name]))
    return None


def reassemble(template: Template, doc: Doc) -> dict[str, Any]:
    """The record of a flattened document, its data nested as the template says."""

    def build(fields: Any, prefix: str) -> dict[str, Any]:
        data: dict[str, Any] = {}
        for name, kind in fields.items():
            path = f"{prefix}{name}"
            data[name] = (
                build(kind.fields, f"{path}.") if isinstance(kind, Container) else doc[path]
            )
        return data

    return {
        "template": template.id,
        "topic": doc["_topic"],
        "robot": doc["_robot"],
        "t": doc["_t"],
        "data": build(template.fields, ""),
    }


def indexed_fields(template: Template) -> list[str]:
    """Leaves with a sorted index: int, float and bool outside arrays."""
    return sorted(
        path
        for path, kind in template.leaves()
        if isinstance(kind, Scalar) and kind.kind in INDEXED_KINDS
    )


Rows = bytes
"""Indexed values of consecutive records, one fixed-width row each (:class:`DocumentForm`)."""
PREFIX = b'{"_i":0,'
"""How a prepared document starts: its index, unknown until its log takes it, is 0."""


class DocumentForm:
    """What the views of a template keep of a record, computed from its canonical bytes
    alone, so that an ingest's staging processes can do it for the commit: the document's
    bytes (exactly those the segment file holds), its indexed values as one fixed-width row
    (``_t`` as int64, every indexed field as float64), and its keyword text."""

    def __init__(self, template: Template) -> None:
        self.flatten = flattener(template)
        self.fields = indexed_fields(template)
        self.row = struct.Struct("<q" + "d" * len(self.fields))
        read = itemgetter("_t", *self.fields)
        self.read_row: Callable[[Doc], tuple[Any, ...]] = (
            read if self.fields else lambda doc: (doc["_t"],)
        )
        self.text_of = keyword_text(template)

    def prepared(self, canonical: bytes) -> tuple[bytes, bytes, str | None]:
        """A record's document (index 0), its row and its text (None without strings)."""
        doc = self.flatten(orjson.loads(canonical), 0)
        text = self.text_of(doc) if self.text_of is not None else None
        return orjson.dumps(doc), self.row.pack(*self.read_row(doc)), text

    def rows_of(self, docs: Sequence[Doc]) -> Rows:
        pack, read = self.row.pack, self.read_row
        return b"".join(pack(*read(doc)) for doc in docs)

    def columns(self, rows: Rows) -> list[Any]:
        """``_t`` and each indexed field's values, one array each."""
        table = np.frombuffer(rows, dtype=np.dtype([("t", "<i8"), ("v", "<f8", len(self.fields))]))
        return [table["t"], *(table["v"][:, n] for n in range(len(self.fields)))]


@dataclass(frozen=True)
class PreparedDocuments:
    """Consecutive records of a template as :class:`DocumentForm` prepared them."""

    docs: list[bytes]
    """Each document's JSON as its spool line holds it, the newline kept."""
    rows: Rows
    row_size: int

    def __len__(self) -> int:
        return len(self.docs)

    def parsed(self, first: int, start: int, stop: int) -> list[Doc]:
        """Documents ``start`` to ``stop - 1`` of these, as dicts, the first at index ``first``."""
        found: list[Doc] = []
        for n, doc in enumerate(self.docs[start:stop], first):
            parsed = orjson.loads(doc)
            parsed["_i"] = n
            found.append(parsed)
        return found

    def rows_between(self, start: int, stop: int) -> Rows:
        return self.rows[start * self.row_size : stop * self.row_size]

    def segment_file(self, first: int, start: int, stop: int) -> bytes:
        """The segment file of documents ``start`` to ``stop - 1``, the first at ``first``:
        the bytes orjson writes for them as TinyDB stores a table (tested)."""
        skip = len(PREFIX)
        items = b",".join(
            b'"%d":{"_i":%d,%s' % (n + 1, first + n, doc[skip:-1])
            for n, doc in enumerate(self.docs[start:stop])
        )
        return b'{"%s":{%s}}' % (TABLE.encode(), items)


@dataclass(frozen=True)
class SealedSegment:
    """One sealed segment: records ``first .. first + count - 1`` and each field's range."""

    first: int
    count: int
    ranges: dict[str, tuple[float, float]]
    """``_t`` and every indexed field: (lowest, highest) value in the segment."""

    @property
    def name(self) -> str:
        return f"seg-{self.first:012d}"

    def to_json(self) -> dict[str, Any]:
        return {"first": self.first, "count": self.count, "ranges": self.ranges}

    @classmethod
    def from_json(cls, document: dict[str, Any]) -> SealedSegment:
        ranges = {key: (value[0], value[1]) for key, value in document["ranges"].items()}
        return cls(int(document["first"]), int(document["count"]), ranges)


@dataclass(frozen=True)
class SortedIndex:
    """A field's values in one segment, sorted, with the position of each."""

    values: array[float] | array[int]
    positions: array[int]

    def between(
        self,
        low: float | None,
        high: float | None,
        *,
        low_open: bool = False,
        high_open: bool = False,
    ) -> array[int]:
        """Positions whose value lies in the range (None: unbounded on that side)."""
        if low is None:
            start = 0
        elif low_open:
            start = bisect.bisect_right(self.values, low)
        else:
            start = bisect.bisect_left(self.values, low)
        if high is None:
            stop = len(self.values)
        elif high_open:
            stop = bisect.bisect_left(self.values, high)
        else:
            stop = bisect.bisect_right(self.values, high)
        return self.positions[start:stop] if start < stop else array("I")


def _index_file(directory: Path, segment: SealedSegment, field: str) -> Path:
    return directory / f"{segment.name}.{field}.idx"


def _write_index(path: Path, column: Any) -> None:
    """Written in place: the manifest written after it is what makes it part of the views.

    A stable sort, so equal values keep their positions in order."""
    order = np.argsort(column, kind="stable")
    write_synced(path, column[order].tobytes() + order.astype(np.uint32).tobytes())


def _read_index(path: Path, count: int, typecode: str) -> SortedIndex:
    data = path.read_bytes()
    values = array(typecode)
    split = count * values.itemsize
    values.frombytes(data[:split])
    positions = array("I")
    positions.frombytes(data[split:])
    if len(values) != count or len(positions) != count:
        raise ValueError(f"{path} does not hold {count} entries")
    return SortedIndex(values, positions)


class SegmentCache:
    """Decoded segment files, least recently used dropped first (shared by templates)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._items: OrderedDict[tuple[str, ...], Any] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: tuple[str, ...], load: Callable[[], Any]) -> Any:
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value = load()
        self.put(key, value)
        return value

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)

    def put(self, key: tuple[str, ...], value: Any) -> None:
        with self._lock:
            self._items[key] = value
            self._items.move_to_end(key)
            while len(self._items) > self.capacity:
                self._items.popitem(last=False)


@dataclass(frozen=True)
class SegmentCaches:
    """Documents and sorted indexes of sealed segments, bounded apart: a segment's documents
    (about 6 MB for 4096 records of an IMU) outweigh one of its indexes (48 kB) a hundredfold,
    so one count for both let memory grow with the number of segments sealed."""

    docs: SegmentCache
    indexes: SegmentCache

    @classmethod
    def holding(cls, segments: int) -> SegmentCaches:
        """The documents of ``segments`` segments and 32 times as many indexes."""
        return cls(SegmentCache(segments), SegmentCache(segments * 32))


class TemplateSegments:
    """The segments and the tail of one template version, under ``directory``."""

    def __init__(
        self, directory: Path, template: Template, segment_records: int, caches: SegmentCaches
    ) -> None:
        self.directory = directory
        self.template = template
        self.segment_records = segment_records
        self.caches = caches
        self.form = DocumentForm(template)
        self.fields = self.form.fields
        self.flatten = self.form.flatten
        """A record (parsed from its canonical bytes) and its index as a document."""
        self._lock = threading.Lock()
        directory.mkdir(parents=True, exist_ok=True)
        self.sealed: list[SealedSegment] = self._open_manifest()
        self.tail: list[Doc] = []

    def _open_manifest(self) -> list[SealedSegment]:
        manifest = self.directory / MANIFEST
        sealed = []
        if manifest.exists():
            document = json.loads(manifest.read_bytes())
            sealed = [SealedSegment.from_json(item) for item in document["sealed"]]
        listed = {f"{segment.name}.json" for segment in sealed} | {MANIFEST}
        listed |= {
            _index_file(self.directory, segment, field).name
            for segment in sealed
            for field in ("_t", *self.fields)
        }
        for path in self.directory.iterdir():
            if path.name not in listed:
                path.unlink()
        return sealed

    @property
    def durable(self) -> int:
        """Records in sealed segments: the views hold these without the log's help."""
        return self.sealed[-1].first + self.sealed[-1].count if self.sealed else 0

    @property
    def size(self) -> int:
        return self.durable + len(self.tail)

    def add(self, docs: Iterable[Doc]) -> None:
        """Add documents in index order; seal full segments with one batch write each.

        The documents are in the tail before any segment is written, so a write that fails
        leaves every one of them held, and the next add seals them.
        """
        with self._lock:
            for doc in docs:
                if doc["_i"] != self.size:
                    raise ValueError(f"document {doc['_i']} arrives at {self.size}")
                self.tail.append(doc)
            self._seal_full_tail()

    def fitting(self, wanted: int) -> int:
        """How many of ``wanted`` records to add next so that the tail ends on a segment
        boundary (whole segments are written from prepared documents; records left in the
        tail are parsed): ``wanted`` itself when no boundary lies within it."""
        room = self.segment_records - len(self.tail) % self.segment_records
        if wanted < room:
            return wanted
        return room + (wanted - room) // self.segment_records * self.segment_records

    def add_prepared(self, first: int, documents: PreparedDocuments) -> None:
        """Add records ``first``... as :class:`DocumentForm` prepared them where they were
        staged: whole segments are written from the documents' bytes and rows, never parsed;
        only records that join the tail (to complete it, or left over) are.

        Like :meth:`add`, every record is held when this returns or raises: a segment that
        cannot be written leaves the rest in the tail, to be sealed by a later add.
        """
        with self._lock:
            if first != self.size:
                raise ValueError(f"document {first} arrives at {self.size}")
            count, at = len(documents.docs), 0
            try:
                if self.tail:
                    at = min(count, self.segment_records - len(self.tail))
                    self.tail += documents.parsed(first, 0, at)
                    self._seal_full_tail()
                while count - at >= self.segment_records:
                    stop = at + self.segment_records
                    segment = SealedSegment(first + at, self.segment_records, {})
                    self._write_segment(
                        segment,
                        documents.segment_file(first + at, at, stop),
                        documents.rows_between(at, stop),
                    )
                    at = stop
            finally:
                self.tail += documents.parsed(first + at, at, count)

    def _seal_full_tail(self) -> None:
        while len(self.tail) >= self.segment_records:
            docs = self.tail[: self.segment_records]
            segment = SealedSegment(docs[0]["_i"], len(docs), {})
            content = orjson.dumps({TABLE: {str(n): doc for n, doc in enumerate(docs, 1)}})
            rows = self.form.rows_of(docs)
            self._write_segment(segment, content, rows)
            self.caches.docs.put((str(self.directory), segment.name), docs)
            self.tail = self.tail[self.segment_records :]

    def _write_segment(self, segment: SealedSegment, content: bytes, rows: Rows) -> None:
        """Write a sealed segment's file (TinyDB's, the one its ``insert_multiple`` writes into
        a fresh database) and its indexes, then list it in the manifest."""
        path = self.directory / f"{segment.name}.json"
        tmp = path.with_name(f".{path.name}.tmp")
        write_synced(tmp, content)
        os.replace(tmp, path)
        for field, column in zip(("_t", *self.fields), self.form.columns(rows), strict=True):
            _write_index(_index_file(self.directory, segment, field), column)
            segment.ranges[field] = (column.min().item(), column.max().item())
        fsync_dir(self.directory)
        sealed = [*self.sealed, segment]
        manifest = {"sealed": [item.to_json() for item in sealed]}
        atomic_write(self.directory / MANIFEST, json.dumps(manifest).encode())
        self.sealed = sealed

    def snapshot(self) -> tuple[list[SealedSegment], list[Doc]]:
        """The sealed segments and the tail as of now, for a query to read without locks."""
        with self._lock:
            return list(self.sealed), list(self.tail)

    def docs(self, segment: SealedSegment) -> list[Doc]:
        """A sealed segment's documents in index order (cached)."""

        def load() -> list[Doc]:
            path = self.directory / f"{segment.name}.json"
            database = TinyDB(path, storage=SegmentStorage, access_mode="r")
            try:
                found = database.table(TABLE).all()
            finally:
                database.close()
            return sorted((dict(doc) for doc in found), key=lambda doc: int(doc["_i"]))

        docs: list[Doc] = self.caches.docs.get((str(self.directory), segment.name), load)
        return docs

    def index(self, segment: SealedSegment, field: str) -> SortedIndex:
        def load() -> SortedIndex:
            typecode = "q" if field == "_t" else "d"
            return _read_index(_index_file(self.directory, segment, field), segment.count, typecode)

        key = (str(self.directory), segment.name, field)
        index: SortedIndex = self.caches.indexes.get(key, load)
        return index

    def docs_between(self, start: int, stop: int) -> list[Doc]:
        """The documents of records ``start`` to ``stop - 1``, all of which the views hold."""
        sealed, tail = self.snapshot()
        found: list[Doc] = []
        for segment in sealed:
            end = segment.first + segment.count
            if segment.first < stop and start < end:
                docs = self.docs(segment)
                found.extend(
                    docs[max(start, segment.first) - segment.first : min(stop, end) - segment.first]
                )
        tail_first = sealed[-1].first + sealed[-1].count if sealed else 0
        found.extend(tail[max(0, start - tail_first) : max(0, stop - tail_first)])
        return found

    def all_docs(self) -> Iterator[Doc]:
        """Every document, sealed then tail, in index order (full scans: the baseline)."""
        sealed, tail = self.snapshot()
        for segment in sealed:
            yield from self.docs(segment)
        yield from tail
