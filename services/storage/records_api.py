"""Routes of templates, records, queries and intervals: parse, call the domain, render."""

from __future__ import annotations

import hashlib
import json
import re
import time
from collections.abc import AsyncIterator, Callable
from typing import Annotated, Any, Literal, TypeVar

import anyio
import orjson
from eth_utils.address import is_address, to_checksum_address
from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field

from robocloud import bounded_json
from robocloud.errors import FormatError
from robocloud.signing import HEADER_SIGNATURE, canonical_request
from robocloud.templates import load_template_document, record_topic, recordable_topic
from services.common.auth import SignedAddress, require_role, verified_request
from services.common.bodies import INLINE_JSON_BYTES, json_body, media_type
from services.common.errors import BadRequest, Forbidden, PayloadTooLarge, UnsupportedMediaType
from services.common.slots import Slots
from services.storage.catalog import Catalog, Status, TemplateVersion
from services.storage.queries import QueryEngine, QueryInvalid, RecordQuery
from services.storage.recordstore import Authorship, RecordRejected, RecordStore, StoredRecord
from services.storage.settings import StorageSettings

router = APIRouter(tags=["records"])

T = TypeVar("T")

TEMPLATE_BODY_LIMIT = 256 * 1024
TEMPLATE_PAGE_BYTES = 1024 * 1024
"""A page of ``GET /v1/templates`` stops once its versions reach this many bytes."""
RECORD_DEPTH = 24
"""JSON nesting of one record: envelope, data, 8 composites with their objects, and slack."""
JSON_TYPES = ("application/json",)
NDJSON_TYPES = ("application/x-ndjson", "application/jsonl", "application/json-seq")


class Review(BaseModel):
    decision: Literal["approve", "reject"]
    reason: str | None = Field(default=None, max_length=1024)


def _catalog(request: Request) -> Catalog:
    catalog: Catalog = request.app.state.catalog
    return catalog


def _store(request: Request) -> RecordStore:
    store: RecordStore = request.app.state.records
    return store


def _version(version: TemplateVersion, status_code: int = 200) -> JSONResponse:
    return JSONResponse(version.to_json(), status_code=status_code)


async def _template_document(request: Request) -> Any:
    if media_type(request) != "application/json":
        raise UnsupportedMediaType(
            "the body must be application/json",
            details={"header": "Content-Type", "received": request.headers.get("content-type")},
        )
    return load_template_document(await request.body())


@router.post("/v1/templates", status_code=201)
async def create_template(request: Request, author: SignedAddress) -> JSONResponse:
    """A new template, version 1, as a draft of the signer."""
    document = await _template_document(request)
    version = await anyio.to_thread.run_sync(
        lambda: _catalog(request).create(document, author=author)
    )
    return _version(version, 201)


@router.post("/v1/templates/{name}/versions", status_code=201)
async def new_template_version(request: Request, name: str, author: SignedAddress) -> JSONResponse:
    """The next version of a template, as a draft of the signer."""
    document = await _template_document(request)
    version = await anyio.to_thread.run_sync(
        lambda: _catalog(request).new_version(name, document, author=author)
    )
    return _version(version, 201)


@router.put("/v1/templates/{template_id}")
async def edit_template(request: Request, template_id: str, author: SignedAddress) -> JSONResponse:
    """Replace a draft's fields (409 once submitted or approved: make a new version)."""
    document = await _template_document(request)
    version = await anyio.to_thread.run_sync(
        lambda: _catalog(request).edit(template_id, document, author=author)
    )
    return _version(version)


@router.post("/v1/templates/{template_id}/submit")
async def submit_template(
    request: Request, template_id: str, author: SignedAddress
) -> JSONResponse:
    version = await anyio.to_thread.run_sync(
        lambda: _catalog(request).submit(template_id, author=author)
    )
    return _version(version)


@router.post("/v1/templates/{template_id}/review")
async def review_template(
    request: Request,
    template_id: str,
    review: Review = Depends(json_body(Review)),
    reviewer: str = require_role("reviewer"),  # type: ignore[assignment]
) -> JSONResponse:
    """Approve or reject a submitted version; the signer must hold the ``reviewer`` role."""
    version = await anyio.to_thread.run_sync(
        lambda: _catalog(request).review(
            template_id, review.decision, reviewer=reviewer, reason=review.reason
        )
    )
    return _version(version)


@router.get("/v1/templates")
async def list_templates(
    request: Request,
    name: str | None = None,
    status: Status | None = None,
    after: str | None = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> dict[str, Any]:
    """Template versions by name and version, at most ``limit`` and about
    ``TEMPLATE_PAGE_BYTES``; ``next`` continues the list. Sorted and encoded on a worker
    thread: a large catalog's page held the event loop for a second."""

    def page() -> dict[str, Any]:
        versions, more = _catalog(request).page(
            name=name, status=status, after=after, limit=limit, max_bytes=TEMPLATE_PAGE_BYTES
        )
        return {
            "templates": [version.to_json() for version in versions],
            "next": versions[-1].id if more else None,
        }

    return await anyio.to_thread.run_sync(page)


@router.get("/v1/templates/{template_id}")
async def get_template(request: Request, template_id: str) -> JSONResponse:
    """One template version. Read on a worker thread: the catalog's lock is held across the
    fsync of each template written."""
    version = await anyio.to_thread.run_sync(_catalog(request).get, template_id)
    return _version(version)


def authorship_of(request: Request) -> Authorship:
    """What a stored record keeps of the signed request that wrote it (records and ingestion)."""
    verified = verified_request(request)
    path = (request.scope.get("raw_path") or request.url.path.encode()).split(b"?", 1)[0]
    query = request.scope.get("query_string", b"").decode("latin-1")
    canonical = canonical_request(
        verified.audience,
        request.method,
        path.decode("latin-1"),
        query,
        verified.timestamp,
        verified.nonce,
        verified.content_sha256,
    )
    return Authorship(
        signer=verified.address,
        audience=verified.audience,
        method=request.method,
        path=path.decode("latin-1"),
        query=query,
        timestamp=verified.timestamp,
        nonce=verified.nonce,
        content_sha256=verified.content_sha256,
        signature=request.headers.get(HEADER_SIGNATURE, ""),
        request_sha256=hashlib.sha256(canonical.encode()).hexdigest(),
        received_at_ns=time.time_ns(),
    )


async def _lines(request: Request, limit: int) -> AsyncIterator[tuple[int, bytes]]:
    """Non-blank NDJSON lines with their record index; 413 for a line over ``limit`` bytes."""
    pending = bytearray()
    index = 0
    async for chunk in request.stream():
        pending += chunk
        while (end := pending.find(b"\n")) >= 0:
            line = bytes(pending[:end]).strip()
            del pending[: end + 1]
            if len(line) > limit:
                raise _line_too_long(index, limit)
            if line:
                yield index, line
                index += 1
        if len(pending) > limit:
            raise _line_too_long(index, limit)
    if pending.strip():
        yield index, bytes(pending).strip()


def _line_too_long(index: int, limit: int) -> PayloadTooLarge:
    return PayloadTooLarge(
        f"record {index} is longer than {limit} bytes",
        details={"index": index, "limit": limit},
    )


def _too_many(limit: int) -> PayloadTooLarge:
    return PayloadTooLarge(
        f"a batch holds at most {limit} records", details={"field": "records", "limit": limit}
    )


def _parsed(index: int, line: bytes) -> Any:
    try:
        return bounded_json.loads(line, max_depth=RECORD_DEPTH)
    except FormatError as exc:
        raise RecordRejected(index, "", str(exc), code="invalid_json") from exc


_BLANK = re.compile(r"[ \t\n\r]*")


def _first_refused_record(body: bytes) -> int | None:
    """The index of the first record of a JSON array body that is refused on its own (NaN,
    a lone surrogate, a syntax error), as NDJSON bodies name theirs; None when the fault is
    outside every record. Only asked once the whole body was refused: a good batch pays
    nothing, and the nesting bound already held for the whole."""
    try:
        text = body.decode()
    except UnicodeDecodeError:
        return None
    decoder = json.JSONDecoder()
    position = _after_blanks(text, 0)
    if not text.startswith("[", position):
        return None
    index = 0
    while True:
        position = _after_blanks(text, position + 1)
        if text.startswith("]", position):
            return None
        try:
            end = decoder.raw_decode(text, position)[1]
            bounded_json.loads(text[position:end], max_depth=RECORD_DEPTH)
        except ValueError:  # json's errors and bounded_json's
            return index
        position = _after_blanks(text, end)
        if not text.startswith(",", position):
            return None
        index += 1


def _after_blanks(text: str, position: int) -> int:
    blanks = _BLANK.match(text, position)
    assert blanks is not None, "the pattern matches the empty string"
    return blanks.end()


async def _records_of(request: Request, settings: StorageSettings) -> list[Any]:
    kind = media_type(request)
    limit = settings.storage_max_batch_records
    if kind in NDJSON_TYPES:
        records = []
        async for index, line in _lines(request, settings.storage_max_line_bytes):
            if index >= limit:
                raise _too_many(limit)
            records.append(_parsed(index, line))
        return records
    if kind not in JSON_TYPES:
        raise UnsupportedMediaType(
            "records are application/json (an array) or application/x-ndjson",
            details={"header": "Content-Type", "received": request.headers.get("content-type")},
        )
    body = await request.body()
    if len(body) > INLINE_JSON_BYTES:
        return await anyio.to_thread.run_sync(_json_records, body, limit)
    return _json_records(body, limit)


def _json_records(body: bytes, limit: int) -> list[Any]:
    """A JSON array of at most ``limit`` records. Parsed on a worker thread past a few
    kilobytes: a batch of 64 MiB took about 3 s of the event loop, twice when it was not
    JSON (to name the record at fault)."""
    try:
        document = bounded_json.loads(body, max_depth=RECORD_DEPTH + 1)
    except bounded_json.JsonDepthError:
        raise
    except bounded_json.JsonError as exc:
        refused = _first_refused_record(body)
        if refused is None:
            raise
        raise RecordRejected(refused, "", str(exc), code="invalid_json") from exc
    if not isinstance(document, list):
        raise BadRequest(
            "the body must be a JSON array of records", code="invalid_body", details={"field": ""}
        )
    if len(document) > limit:
        raise _too_many(limit)
    return document


@router.post("/v1/records", status_code=201)
async def append_records(request: Request) -> dict[str, Any]:
    """Store a batch of records (all or none); their ids in the order sent."""
    author = authorship_of(request)
    records = await _records_of(request, request.app.state.settings)
    _check_written_by_signer(records, author.signer)
    ids = await anyio.to_thread.run_sync(lambda: _store(request).append(records, author=author))
    return {"ids": ids, "count": len(ids)}


def _check_written_by_signer(records: list[Any], signer: str) -> None:
    """A robot writes its own records: every query, interval and export by ``robot`` trusts
    the field, so one naming another robot than the signer is refused, as ingestion sets it.

    Only a well-formed address is compared; anything else is left to the record's checks.
    """
    for index, record in enumerate(records):
        robot = record.get("robot") if isinstance(record, dict) else None
        if isinstance(robot, str) and is_address(robot) and robot.lower() != signer.lower():
            raise Forbidden(
                f"record {index} names robot {robot}, but {signer} signed the batch: a robot "
                "writes only its own records",
                code="robot_not_signer",
                details={"index": index, "robot": robot, "signer": signer},
            )


def _rendered(stored: StoredRecord, meta: bool = False) -> dict[str, Any]:
    rendered: dict[str, Any] = {
        "id": stored.id,
        "record": stored.record,
        "signer": stored.meta.get("signer"),
    }
    if meta:
        rendered["meta"] = stored.meta
    return rendered


def topic_filter(topic: str | None) -> str | None:
    """A query's ``topic`` as records hold it: the bag's own name works, with or without the
    leading ``/`` that a ROS 1 bag may leave out (as a binding's does)."""
    if topic is None:
        return None
    if not recordable_topic(topic):
        raise QueryInvalid("topic", f"{topic[:80]!r} is not a ROS topic name")
    return record_topic(topic)


def robot_filter(robot: str | None) -> str | None:
    """A query's ``robot`` as a checksummed address (records, intervals, export)."""
    if robot is None:
        return None
    if not is_address(robot):
        raise QueryInvalid("robot", f"{robot[:80]!r} is not an address")
    return to_checksum_address(robot)


class RecordFilters:
    """The filters ``GET /v1/records`` and ``GET /v1/export`` share, parsed once for both."""

    def __init__(
        self,
        template: str | None = None,
        topic: Annotated[str | None, Query(max_length=256)] = None,
        robot: str | None = None,
        start: Annotated[int | None, Query(ge=0, description="t >= start (ns)")] = None,
        end: Annotated[int | None, Query(ge=0, description="t < end (ns)")] = None,
        where: Annotated[list[str] | None, Query(description="field op value, AND")] = None,
        keywords: Annotated[str | None, Query(max_length=1024)] = None,
    ) -> None:
        self.template, self.robot = template, robot_filter(robot)
        self.topic = topic_filter(topic)
        self.start, self.end, self.keywords = start, end, keywords
        self.where = tuple(where or ())

    def query(self, limit: int, cursor: str | None = None) -> RecordQuery:
        return RecordQuery(
            template=self.template,
            topic=self.topic,
            robot=self.robot,
            start=self.start,
            end=self.end,
            where=self.where,
            keywords=self.keywords,
            limit=limit,
            cursor=cursor,
        )


async def in_query_slot(request: Request, work: Callable[[], T]) -> T:
    """``work`` (a query: up to a million documents scanned, free for a stranger) on a worker
    thread in one of the few query slots (``services.common.slots``); 503 ``busy`` when
    none frees in time."""
    slots: Slots = request.app.state.query_slots
    return await slots.run_sync(work)


@router.get("/v1/records")
async def query_records(
    request: Request,
    filters: Annotated[RecordFilters, Depends()],
    limit: int = 100,
    cursor: str | None = None,
) -> dict[str, Any]:
    """Records matching every filter, in log order; ``next`` is the cursor of the next page."""
    query = filters.query(limit, cursor)
    engine: QueryEngine = request.app.state.queries
    page = await in_query_slot(request, lambda: engine.records(query))
    return {
        "records": [_rendered(stored) for stored in page.records],
        "next": page.next,
        "keywords_pending": page.keywords_pending,
    }


@router.get("/v1/records/{record_id}")
async def get_record(request: Request, record_id: str) -> dict[str, Any]:
    """One record exactly as logged, with who signed the request that stored it."""
    stored = await anyio.to_thread.run_sync(_store(request).get, record_id)
    return _rendered(stored, meta=True)


@router.get("/v1/intervals")
async def state_intervals(
    request: Request,
    template: str,
    field: str,
    value: str,
    robot: str | None = None,
    start: Annotated[int | None, Query(ge=0)] = None,
    end: Annotated[int | None, Query(ge=0)] = None,
) -> Response:
    """When each robot entered and left the state ``field == value`` (exit null: still in).

    Rendered and encoded in the query's turn: a state that toggles often in a wide window
    has up to a million intervals, seconds of the event loop's time."""
    engine: QueryEngine = request.app.state.queries

    def answer() -> bytes:
        intervals = engine.intervals(
            template, field, value, robot=robot_filter(robot), start=start, end=end
        )
        return orjson.dumps(
            {
                "template": template,
                "field": field,
                "value": value,
                "intervals": [interval.to_json() for interval in intervals],
            }
        )

    return Response(await in_query_slot(request, answer), media_type="application/json")
