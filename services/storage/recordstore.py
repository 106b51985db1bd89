"""The record store: validated records into the logs, then into their views.

``append`` checks a whole batch before anything is written (every record against its
approved template), moves large arrays to cas (the record then holds the array's CID; images
and files arrive as CIDs already), appends each template's records to its log in one durable
group commit, and only then derives the views: TinyDB segments with their indexes (in the
same call) and keywords (a background thread, see ``keywords.py``). Views are rebuilt past
their durable mark at open, so a kill -9 anywhere leaves every acknowledged record in them
exactly once.

Each log entry's ``meta`` keeps who wrote the record: the signer, the signed request's
fields and its signature, so that authorship can be checked by anyone holding the entry.
"""

from __future__ import annotations

import contextlib
import gc
import json
import logging
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, NamedTuple

import orjson

from robocloud.proofs import RecordId
from robocloud.templates import (
    ArrayOf,
    RecordInvalid,
    Template,
    canonical_part,
    canonical_record,
    check_envelope,
    parse_template_id,
)
from services.storage.catalog import Catalog, TemplateNotApproved, TemplateNotFound
from services.storage.keywords import KeywordIndex
from services.storage.recordlog import EntryNotFound, LogEntry, RecordLogs
from services.storage.segments import (
    PreparedDocuments,
    SegmentCaches,
    TemplateSegments,
    keyword_text,
)

log = logging.getLogger("robocloud.storage.records")

KEYWORD_BATCH = 16384
"""Records per keyword commit: a Whoosh commit writes a segment, and a batch's repeated
strings make one document each."""
READ_BATCH = 4096
KEYWORD_TEXTS_HELD = 262_144
"""Keyword texts held for the keyword thread at most (a few MB); past it, the thread reads
them from the segments, as for live records."""

Offload = Callable[[Sequence[bytes]], list[str]]
"""Stores blobs in cas and returns their CIDs (text), in order."""


@dataclass(frozen=True)
class Authorship:
    """Who wrote a batch: the verified signature of the request that carried it."""

    signer: str
    audience: str
    method: str
    path: str
    query: str
    timestamp: int
    nonce: str
    content_sha256: str
    signature: str
    request_sha256: str
    """SHA-256 of the canonical signed request (ROBOCLOUD-REQUEST-V2 text)."""
    received_at_ns: int

    def meta(self) -> bytes:
        return json.dumps(asdict(self), separators=(",", ":"), sort_keys=True).encode()


class RecordRejected(RecordInvalid):
    """Record ``index`` of a batch is refused; nothing of the batch was stored."""

    def __init__(self, index: int, path: str, message: str, code: str = "invalid_record") -> None:
        super().__init__(path, message)
        self.index = index
        self.code = code
        self.args = (f"record {index}: {path or 'record'}: {message}",)


class RecordNotFound(LookupError):
    def __init__(self, record_id: str) -> None:
        super().__init__(f"no record {record_id}")
        self.record_id = record_id


class OffloadFailed(Exception):
    """cas refused or could not be reached while storing a large array; nothing was stored."""

    def __init__(self, index: int, path: str, reason: str) -> None:
        super().__init__(f"record {index}: {path}: storing the array in cas failed: {reason}")
        self.index = index
        self.path = path


@contextlib.contextmanager
def _views_behind_disk(template_id: str) -> Iterator[None]:
    """Views that could not write a segment (a full disk) after the log committed: logged,
    not raised. The records are durable and the views hold them in memory, sealing them on a
    later add; raising answered a stored request as failed (its retry stored it twice) and
    left the batch's other templates without it, refusing their writes until a restart."""
    try:
        yield
    except OSError as exc:
        log.warning(
            "a segment was not written; its records wait in memory",
            extra={"template": template_id, "error": str(exc)},
        )


def record_id(template_id: str, index: int) -> str:
    name, version = parse_template_id(template_id)
    return f"{name}-{version}-{index}"


class EncodedRecord(NamedTuple):
    """A checked record as its log will hold it: large arrays in cas, its canonical bytes.

    A tuple: an ingest job makes one per record it commits."""

    template_id: str
    record: dict[str, Any]
    canonical: bytes


@dataclass(frozen=True)
class SpooledRecords:
    """Consecutive records of one template as an ingest staged them: canonical bytes, the
    documents their views keep, and their keyword texts (None for a template without)."""

    canonicals: list[bytes]
    documents: PreparedDocuments
    texts: list[bytes] | None
    """As JSON strings: the keyword thread decodes each distinct one once."""


@dataclass(frozen=True)
class StoredRecord:
    id: str
    record: dict[str, Any]
    meta: dict[str, Any]


NUMBER_CHARACTERS = 25
"""The longest canonical number a record's data holds, with its comma: a float's 24
(-1.7976931348623157e+308), an I-JSON integer's 17."""


def _certainly_inline(values: list[Any], limit: int) -> bool:
    """Whether an array of numbers is short enough that its canonical bytes fit under
    ``limit`` whatever they are, so it need not be serialized to be measured."""
    if len(values) * NUMBER_CHARACTERS + 2 > limit:
        return False
    return all(type(value) in (int, float, bool) for value in values)


def _array_leaves(template: Template) -> list[tuple[list[str], ArrayOf]]:
    return [
        (path.split("."), kind) for path, kind in template.leaves() if isinstance(kind, ArrayOf)
    ]


def _replaced(data: dict[str, Any], parts: list[str], value: Any) -> dict[str, Any]:
    """A copy of ``data`` with the value at ``parts`` replaced; only the path is copied."""
    copy = dict(data)
    if len(parts) == 1:
        copy[parts[0]] = value
    else:
        copy[parts[0]] = _replaced(data[parts[0]], parts[1:], value)
    return copy


Checked = tuple[Template, dict[str, Any], bytes]
"""A record checked against its template, and its canonical bytes."""


@dataclass(frozen=True)
class ArrayOffload:
    """Where a record's large arrays go: arrays whose canonical bytes exceed ``inline_bytes``
    are stored through ``offload`` and the record holds their CID (None: refused, this node
    has no cas)."""

    inline_bytes: int
    offload: Offload | None

    def encoded(
        self, template: Template, record: dict[str, Any], canonical: bytes, position: int = 0
    ) -> EncodedRecord:
        """:meth:`encoded_all` of one record, ``position`` of its batch."""
        (one,) = self.encoded_all([(template, record, canonical)], first=position)
        return one

    def encoded_all(self, records: Sequence[Checked], first: int = 0) -> list[EncodedRecord]:
        """Each record with every array larger than the inline bound replaced by its cas
        CID, the arrays of all of them stored in one call of ``offload``: a batch of laser
        scans posted to ``/v1/records`` was one signed ``add`` an array.

        A record whose canonical bytes fit under the bound holds no such array. Raises
        :class:`OffloadFailed` naming the first record with such an array (its position in
        the batch, counted from ``first``) and the array's field: nothing is stored then."""
        large = [self._large_arrays(*checked) for checked in records]
        blobs = [encoded for arrays in large for _, encoded in arrays]
        cids = iter(self._stored(blobs, large, first) if blobs else [])
        return [
            _with_cids(checked, arrays, cids)
            for checked, arrays in zip(records, large, strict=True)
        ]

    def _large_arrays(
        self, template: Template, record: dict[str, Any], canonical: bytes
    ) -> list[tuple[list[str], bytes]]:
        """The path and canonical bytes of each array of ``record`` past the bound."""
        if len(canonical) <= self.inline_bytes:
            return []
        data = record["data"]
        found = []
        for parts, kind in _array_leaves(template):
            value: Any = data
            for part in parts:
                value = value[part]
            if not isinstance(value, list) or _certainly_inline(value, self.inline_bytes):
                continue
            encoded = canonical_part(value, kind)
            if len(encoded) > self.inline_bytes:
                found.append((parts, encoded))
        return found

    def _stored(
        self, blobs: list[bytes], large: list[list[tuple[list[str], bytes]]], first: int
    ) -> list[str]:
        position, parts = next(
            (first + n, arrays[0][0]) for n, arrays in enumerate(large) if arrays
        )
        path = "data." + ".".join(parts)
        if self.offload is None:
            raise OffloadFailed(position, path, "this node has no cas to store arrays in")
        try:
            cids = self.offload(blobs)
        except Exception as exc:
            raise OffloadFailed(position, path, str(exc)) from exc
        if len(cids) != len(blobs):
            raise OffloadFailed(position, path, f"{len(blobs)} arrays stored as {len(cids)}")
        return cids


def _with_cids(
    checked: Checked, arrays: list[tuple[list[str], bytes]], cids: Iterator[str]
) -> EncodedRecord:
    """The record with each of ``arrays`` replaced by the next of ``cids``."""
    template, record, canonical = checked
    if not arrays:
        return EncodedRecord(template.id, record, canonical)
    data = record["data"]
    for parts, _ in arrays:
        data = _replaced(data, parts, next(cids))
    stored = {**record, "data": data}
    return EncodedRecord(template.id, stored, canonical_record(stored))


YOUNG_COLLECTION_EVERY = 1_000_000
"""Allocations between two collections of the youngest generation (Python's default: 700)."""


def collect_garbage_less_often() -> None:
    """Tune this process's cyclic garbage collector for a storage node.

    A storage node keeps millions of live containers (decoded segments, the views' tails) and
    ingestion allocates a few dicts per record, so at the default the collector keeps
    rescanning what is alive: committing 200,000 records took 8.3 s, 4.9 s with young
    collections every 50,000 allocations, and 4.2 s every 1,000,000 (the collector's own time
    went from 0.9 s to 0.04 s: a young collection scans the batch being committed, whatever
    the threshold, so fewer collections scan less). Records hold no reference cycles; the
    collector still runs, only less often.
    """
    _, middle, old = gc.get_threshold()
    gc.set_threshold(YOUNG_COLLECTION_EVERY, middle, old)


class RecordStore:
    """Records of every approved template: the logs, and views derived from them."""

    def __init__(
        self,
        root: Path,
        logs: RecordLogs,
        catalog: Catalog,
        *,
        segment_records: int = 4096,
        segment_cache: int = 16,
        array_inline_bytes: int = 4096,
        offload: Offload | None = None,
        notify: Callable[[int], None] | None = None,
    ) -> None:
        self.logs = logs
        self.catalog = catalog
        self.segment_records = segment_records
        self.arrays = ArrayOffload(array_inline_bytes, offload)
        self.notify = notify
        self.views_dir = root / "views"
        self.caches = SegmentCaches.holding(segment_cache)
        self._write_lock = threading.Lock()
        self._views: dict[str, TemplateSegments] = {}
        self._views_lock = threading.Lock()
        for template_id in logs.template_ids():
            self._rebuild(template_id)
        self.keywords = KeywordIndex(root / "keywords")
        self._wake = threading.Event()
        self._texts_lock = threading.Lock()
        self._held_texts: dict[str, dict[int, list[bytes]]] = {}
        """Keyword texts of records an ingest committed, by template and first index."""
        self._texts_held = 0
        self._keyword_lock = threading.Lock()
        """Whoosh takes one writer at a time: the background thread and a caller of
        :meth:`index_keywords` take turns."""
        self._stop = threading.Event()
        self._keyword_thread = threading.Thread(
            target=self._index_keywords_forever, name="storage-keywords", daemon=True
        )
        self._keyword_thread.start()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._keyword_thread.join()
        self.keywords.close()

    def views(self, template_id: str) -> TemplateSegments | None:
        with self._views_lock:
            return self._views.get(template_id)

    def template_ids(self) -> list[str]:
        with self._views_lock:
            return sorted(self._views)

    def _open_views(self, template_id: str) -> TemplateSegments:
        with self._views_lock:
            views = self._views.get(template_id)
            if views is None:
                template = self.catalog.get(template_id).template
                views = TemplateSegments(
                    self.views_dir / template_id, template, self.segment_records, self.caches
                )
                self._views[template_id] = views
            return views

    def _rebuild(self, template_id: str) -> None:
        """Bring a template's segments up to its log: what lies past their durable mark."""
        views = self._open_views(template_id)
        size = self.logs.size(template_id)
        if views.durable > size:
            raise RuntimeError(f"{template_id}: views hold {views.durable} records, log {size}")
        start = views.durable
        while start < size:
            stop = min(size, start + READ_BATCH)
            entries = self.logs.entries(template_id, start, stop)
            views.add(
                views.flatten(orjson.loads(e.record), start + n) for n, e in enumerate(entries)
            )
            start = stop
        if size:
            log.info("views rebuilt", extra={"template": template_id, "records": size})

    def encode(self, records: Sequence[Any]) -> list[EncodedRecord]:
        """Check every record against its approved template (the first problem refuses all,
        before anything reaches cas), then move large arrays to cas: what :meth:`append_encoded`
        logs.

        Raises :class:`RecordRejected` (naming the record and field path), or
        :class:`OffloadFailed` when cas cannot take a large array.
        """
        checked = [self._checked(position, record) for position, record in enumerate(records)]
        return self.arrays.encoded_all(checked)

    def encode_of(self, template: Template, record: Any) -> EncodedRecord:
        """:meth:`encode` of one record of ``template``, which the caller already holds
        approved (an ingest job looks its templates up once, not once a message).

        Raises :class:`RecordInvalid` naming the field path, or :class:`OffloadFailed`.
        """
        return self.arrays.encoded(template, record, template.encoder.canonical(record))

    def _checked(self, position: int, record: Any) -> tuple[Template, dict[str, Any], bytes]:
        try:
            template = self.catalog.approved(check_envelope(record))
            return template, record, template.encoder.canonical_enveloped(record)
        except TemplateNotFound as exc:
            raise RecordRejected(position, "template", str(exc), code="template_not_found") from exc
        except TemplateNotApproved as exc:
            raise RecordRejected(
                position, "template", str(exc), code="template_not_approved"
            ) from exc
        except RecordInvalid as exc:
            raise RecordRejected(position, exc.path, exc.reason) from exc

    def append(self, records: Sequence[Any], *, author: Authorship) -> list[str]:
        """Validate, offload, log durably and index ``records``; their ids in the same order.

        Raises as :meth:`encode` does, before anything is stored.
        """
        return self.append_encoded(self.encode(records), author=author)

    def append_encoded(self, records: Sequence[EncodedRecord], *, author: Authorship) -> list[str]:
        """Log durably and index records :meth:`encode` made; their ids in the same order.

        One log batch whatever templates the records name: a request is stored whole or not
        at all, through a crash too, so a client's retry never stores a part twice.
        """
        if not records:
            return []
        meta = author.meta()
        groups: dict[str, list[tuple[int, EncodedRecord]]] = {}
        for position, encoded in enumerate(records):
            groups.setdefault(encoded.template_id, []).append((position, encoded))
        ids: list[str] = [""] * len(records)
        with self._write_lock:
            firsts = self.logs.append_batch(
                {
                    template_id: [LogEntry(record=item.canonical, meta=meta) for _, item in items]
                    for template_id, items in groups.items()
                }
            )
            for template_id, items in groups.items():
                views = self._open_views(template_id)
                first = firsts[template_id]
                if first != views.size:
                    raise RuntimeError(f"{template_id}: log at {first}, views at {views.size}")
                with _views_behind_disk(template_id):
                    views.add(
                        views.flatten(item.record, first + n) for n, (_, item) in enumerate(items)
                    )
                prefix = record_id(template_id, 0)[:-1]
                for n, (position, _) in enumerate(items, first):
                    ids[position] = f"{prefix}{n}"
        self._wake.set()
        if self.notify is not None:
            self.notify(len(records))
        return ids

    def fitting(self, template_id: str, wanted: int) -> int:
        """How many records of ``template_id`` to append next, at most ``wanted``, for its
        views to write whole segments (see ``TemplateSegments.fitting``)."""
        return self._open_views(template_id).fitting(wanted)

    def append_prepared(
        self, template_id: str, batch: SpooledRecords, *, author: Authorship
    ) -> int:
        """Log durably and index consecutive records of one template that an ingest staged
        with their documents prepared (:class:`~services.storage.segments.DocumentForm`);
        the index of the first. Their keyword texts are held for the keyword thread, which
        would otherwise read them back from the segments."""
        meta = author.meta()
        with self._write_lock:
            views = self._open_views(template_id)
            entries = [LogEntry(record=canonical, meta=meta) for canonical in batch.canonicals]
            first = self.logs.append(template_id, entries)
            if first != views.size:
                raise RuntimeError(f"{template_id}: log at {first}, views at {views.size}")
            with _views_behind_disk(template_id):
                views.add_prepared(first, batch.documents)
            if batch.texts is not None:
                self._hold_texts(template_id, first, batch.texts)
        self._wake.set()
        if self.notify is not None:
            self.notify(len(entries))
        return first

    def _hold_texts(self, template_id: str, first: int, texts: list[bytes]) -> None:
        with self._texts_lock:
            if self._texts_held + len(texts) <= KEYWORD_TEXTS_HELD:
                self._held_texts.setdefault(template_id, {})[first] = texts
                self._texts_held += len(texts)

    def _take_texts(self, template_id: str, start: int) -> list[str]:
        """Held texts of records ``start``... (consecutive batches, up to a keyword batch),
        dropping those the keyword index has passed; empty when none are held from there."""
        taken: list[bytes] = []
        with self._texts_lock:
            held = self._held_texts.get(template_id, {})
            for first in [first for first in held if first < start]:
                self._texts_held -= len(held.pop(first))
            while start + len(taken) in held and len(taken) < KEYWORD_BATCH:
                texts = held.pop(start + len(taken))
                self._texts_held -= len(texts)
                taken += texts
        decoded = {text: orjson.loads(text) for text in set(taken)}
        return [decoded[text] for text in taken]

    def get(self, text: str) -> StoredRecord:
        """A record by id, exactly as its log holds it, with its authorship."""
        parsed = RecordId.parse(text)
        template_id, index = parsed.template, parsed.index
        try:
            entry = self.logs.entry(template_id, index)
        except (EntryNotFound, LookupError) as exc:
            raise RecordNotFound(text) from exc
        return StoredRecord(text, json.loads(entry.record), json.loads(entry.meta))

    def read(self, template_id: str, indexes: Sequence[int]) -> Iterator[StoredRecord]:
        """Records of ``template_id`` at ``indexes`` from its log."""
        for index in indexes:
            entry = self.logs.entry(template_id, index)
            yield StoredRecord(
                record_id(template_id, index), json.loads(entry.record), json.loads(entry.meta)
            )

    def keywords_pending(self) -> int:
        """Records written but not yet in the keyword index."""
        pending = 0
        for template_id in self.template_ids():
            views = self.views(template_id)
            if views is not None and keyword_text(views.template) is not None:
                pending += max(0, self.logs.size(template_id) - self.keywords.mark(template_id))
        return pending

    def _index_keywords_forever(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(1.0)
            self._wake.clear()
            try:
                self.index_keywords()
            except Exception:
                log.exception("keyword indexing failed; retrying")
                self._stop.wait(1.0)

    def index_keywords(self) -> None:
        """Index every template's records past its keyword mark, in batches."""
        with self._keyword_lock:
            self._index_keywords()

    def _index_keywords(self) -> None:
        for template_id in self.template_ids():
            views = self.views(template_id)
            if views is None:
                continue
            text_of = keyword_text(views.template)
            if text_of is None:
                continue
            start = self.keywords.mark(template_id)
            size = views.size
            while start < size and not self._stop.is_set():
                texts = self._take_texts(template_id, start)
                if texts:
                    stop = start + len(texts)
                else:
                    stop = min(size, start + KEYWORD_BATCH)
                    texts = list(map(text_of, views.docs_between(start, stop)))
                self.keywords.add(template_id, start, texts, stop)
                start = stop
