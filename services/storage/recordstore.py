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

import json
import logging
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from robocloud import jcs
from robocloud.proofs import RecordId
from robocloud.templates import (
    ArrayOf,
    RecordInvalid,
    Scalar,
    Template,
    canonical_record,
    check_envelope,
    parse_template_id,
    validate_data,
)
from services.storage.catalog import Catalog, TemplateNotApproved, TemplateNotFound
from services.storage.keywords import KeywordIndex
from services.storage.recordlog import EntryNotFound, LogEntry, RecordLogs
from services.storage.segments import SegmentCache, TemplateSegments, flatten

log = logging.getLogger("robocloud.storage.records")

KEYWORD_BATCH = 2000
READ_BATCH = 4096

Offload = Callable[[bytes], str]
"""Stores bytes in cas and returns their CID (text)."""


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


def record_id(template_id: str, index: int) -> str:
    name, version = parse_template_id(template_id)
    return f"{name}-{version}-{index}"


@dataclass(frozen=True)
class StoredRecord:
    id: str
    record: dict[str, Any]
    meta: dict[str, Any]


def _string_leaves(template: Template) -> list[str]:
    return [
        path
        for path, kind in template.leaves()
        if isinstance(kind, Scalar) and kind.kind == "string"
    ]


NUMBER_CHARACTERS = 25
"""The longest canonical number a record's data holds, with its comma: a float's 24
(-1.7976931348623157e+308), an I-JSON integer's 17."""


def _certainly_inline(values: list[Any], limit: int) -> bool:
    """Whether an array of numbers is short enough that its canonical bytes fit under
    ``limit`` whatever they are, so it need not be serialized to be measured."""
    if len(values) * NUMBER_CHARACTERS + 2 > limit:
        return False
    return all(type(value) in (int, float, bool) for value in values)


def _array_leaves(template: Template) -> list[list[str]]:
    return [path.split(".") for path, kind in template.leaves() if isinstance(kind, ArrayOf)]


def _replaced(data: dict[str, Any], parts: list[str], value: Any) -> dict[str, Any]:
    """A copy of ``data`` with the value at ``parts`` replaced; only the path is copied."""
    copy = dict(data)
    if len(parts) == 1:
        copy[parts[0]] = value
    else:
        copy[parts[0]] = _replaced(data[parts[0]], parts[1:], value)
    return copy


class RecordStore:
    """Records of every approved template: the logs, and views derived from them."""

    def __init__(
        self,
        root: Path,
        logs: RecordLogs,
        catalog: Catalog,
        *,
        segment_records: int = 4096,
        segment_cache: int = 64,
        array_inline_bytes: int = 4096,
        offload: Offload | None = None,
        notify: Callable[[int], None] | None = None,
    ) -> None:
        self.logs = logs
        self.catalog = catalog
        self.segment_records = segment_records
        self.array_inline_bytes = array_inline_bytes
        self.offload = offload
        self.notify = notify
        self.views_dir = root / "views"
        self.cache = SegmentCache(segment_cache * 8)
        self._write_lock = threading.Lock()
        self._views: dict[str, TemplateSegments] = {}
        self._views_lock = threading.Lock()
        for template_id in logs.template_ids():
            self._rebuild(template_id)
        self.keywords = KeywordIndex(root / "keywords")
        self._wake = threading.Event()
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
                    self.views_dir / template_id, template, self.segment_records, self.cache
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
            views.add(flatten(json.loads(e.record), start + n) for n, e in enumerate(entries))
            start = stop
        if size:
            log.info("views rebuilt", extra={"template": template_id, "records": size})

    def _checked(self, records: Sequence[Any]) -> list[tuple[str, Template]]:
        """Each record's template id and approved template; the first problem refuses all."""
        checked = []
        for position, record in enumerate(records):
            try:
                template_id = check_envelope(record)
                template = self.catalog.approved(template_id)
                validate_data(template, record["data"])
            except TemplateNotFound as exc:
                raise RecordRejected(
                    position, "template", str(exc), code="template_not_found"
                ) from exc
            except TemplateNotApproved as exc:
                raise RecordRejected(
                    position, "template", str(exc), code="template_not_approved"
                ) from exc
            except RecordInvalid as exc:
                raise RecordRejected(position, exc.path, exc.reason) from exc
            checked.append((template_id, template))
        return checked

    def _offloaded(self, position: int, record: dict[str, Any], template: Template) -> Any:
        """``record`` with every array larger than the inline bound replaced by its cas CID."""
        data = record["data"]
        for parts in _array_leaves(template):
            value: Any = data
            for part in parts:
                value = value[part]
            if not isinstance(value, list) or _certainly_inline(value, self.array_inline_bytes):
                continue
            encoded = jcs.canonical(value)
            if len(encoded) <= self.array_inline_bytes:
                continue
            path = "data." + ".".join(parts)
            if self.offload is None:
                raise OffloadFailed(position, path, "this node has no cas to store arrays in")
            try:
                cid = self.offload(encoded)
            except Exception as exc:
                raise OffloadFailed(position, path, str(exc)) from exc
            data = _replaced(data, parts, cid)
        return {**record, "data": data} if data is not record["data"] else record

    def append(self, records: Sequence[Any], *, author: Authorship) -> list[str]:
        """Validate, offload, log durably and index ``records``; their ids in the same order.

        Raises :class:`RecordRejected` (naming the record and field path) before anything is
        stored, or :class:`OffloadFailed` when cas cannot take a large array.
        """
        if not records:
            return []
        checked = self._checked(records)
        meta = author.meta()
        groups: dict[str, list[tuple[int, dict[str, Any], bytes]]] = {}
        for position, (record, (template_id, template)) in enumerate(
            zip(records, checked, strict=True)
        ):
            stored = self._offloaded(position, record, template)
            groups.setdefault(template_id, []).append((position, stored, canonical_record(stored)))
        ids: list[str] = [""] * len(records)
        with self._write_lock:
            for template_id, items in groups.items():
                views = self._open_views(template_id)
                first = self.logs.append(
                    template_id, [LogEntry(record=data, meta=meta) for _, _, data in items]
                )
                if first != views.size:
                    raise RuntimeError(f"{template_id}: log at {first}, views at {views.size}")
                views.add(flatten(stored, first + n) for n, (_, stored, _) in enumerate(items))
                for n, (position, _, _) in enumerate(items):
                    ids[position] = record_id(template_id, first + n)
        self._wake.set()
        if self.notify is not None:
            self.notify(len(records))
        return ids

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
            if views is not None and _string_leaves(views.template):
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
            strings = _string_leaves(views.template)
            if not strings:
                continue
            start = self.keywords.mark(template_id)
            size = self.logs.size(template_id)
            while start < size and not self._stop.is_set():
                stop = min(size, start + KEYWORD_BATCH)
                texts = []
                for n, entry in enumerate(self.logs.entries(template_id, start, stop)):
                    doc = flatten(json.loads(entry.record), start + n)
                    text = " ".join(str(doc[path]) for path in strings)
                    texts.append((start + n, text))
                self.keywords.add(template_id, texts, stop)
                start = stop
