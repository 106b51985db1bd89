"""Routes of bag ingestion, jobs, bindings and exports: parse, call the domain, render."""

from __future__ import annotations

import hashlib
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, BinaryIO, Literal

import anyio
from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse, StreamingResponse
from pydantic import BaseModel, Field

from robocloud.cid import CID, parse_cid
from robocloud.ingest import FINISHED
from robocloud.semantic import MCAP_MEDIA_TYPE
from services.common.bodies import (
    SMALL_JSON_BODY,
    bounded_stream,
    json_body,
    media_type,
    wait_parameter,
)
from services.common.changes import long_poll
from services.common.errors import Unprocessable, UnsupportedMediaType
from services.common.pipeline import batched, entered_in_worker_thread, in_worker_thread
from services.common.responses import stream_in_turn
from services.common.slots import Slots
from services.storage.bags import SUFFIXES, detect_format
from services.storage.casbags import BagBounds, fetch_bag
from services.storage.export import Encoder, JsonLinesEncoder, McapEncoder
from services.storage.ingest import IngestJobs
from services.storage.matcher import Bindings
from services.storage.queries import Page, QueryEngine
from services.storage.records_api import RecordFilters, authorship_of, in_query_slot

if TYPE_CHECKING:
    from hashlib import _Hash as Hash

router = APIRouter(tags=["ingest"])
MAX_UPDATED_NS = 2**63 - 1
"""A job's ``updated_ns`` (nanoseconds since the epoch) fits in a signed 64-bit integer."""
JSON = "application/json"
EXPORT_PAGE = 1000
EXPORT_FORMATS = {
    "mcap": (MCAP_MEDIA_TYPE, "export.mcap"),
    "jsonl": ("application/x-ndjson", "export.jsonl"),
}
"""Each export format's media type and file name."""


class IngestFromCas(BaseModel):
    cid: str = Field(max_length=256, description="a bag file or a ROS 2 bag directory in cas")


_named_bag = json_body(IngestFromCas, max_bytes=SMALL_JSON_BODY)
"""``{"cid"}``, a few hundred bytes, not the route's limit of a bag upload."""


class Binding(BaseModel):
    template: str = Field(max_length=80)
    topic: str | None = Field(default=None, max_length=300)
    msgtype: str | None = Field(default=None, max_length=300)


def _jobs(request: Request) -> IngestJobs:
    jobs: IngestJobs = request.app.state.ingest_jobs
    return jobs


async def _spool_upload(request: Request, spool: Path, limit: int) -> tuple[Path, str]:
    """The streamed body in a file of ``spool`` named by its format (rosbags needs the
    suffix); whatever it leaves there on failure goes with ``spool``. The bag is hashed and
    written on a worker thread, a batch at a time while the next arrives: hashing 16 GiB
    alone took 11 s of the event loop's time in slices, and a write the kernel throttled
    once its dirty pages piled up held every route of the service."""
    digest = hashlib.sha256()
    path = spool / "upload"
    with path.open("wb") as handle:
        body = bounded_stream(request, limit, "a bag upload")
        await in_worker_thread(
            batched(body, UPLOAD_BATCH_BYTES), lambda chunks: _spooled(chunks, digest, handle)
        )
    named = path.with_name(f"bag{SUFFIXES.get(detect_format(path), '')}")
    path.rename(named)
    return named, f"upload:{digest.hexdigest()}"


UPLOAD_BATCH_BYTES = 1 << 20
"""What an upload hands its worker thread at a time."""


def _spooled(chunks: list[bytes], digest: Hash, spool: BinaryIO) -> None:
    """Hash ``chunks`` and write them to ``spool``."""
    for chunk in chunks:
        digest.update(chunk)
        spool.write(chunk)


@router.post("/v1/ingest", status_code=202)
async def ingest(request: Request) -> JSONResponse:
    """Ingest a bag: a JSON body ``{"cid"}`` names one in cas (a file, or a directory for a
    split ROS 2 bag); any other body is the bag file itself, streamed. Answers the job: a
    resend while the robot's job of the bag runs gets that job before the bag is read (an
    upload is named by the digest its signature covers). The bag's spool is made and
    removed on a worker thread: a bag refused (too large, too many jobs, a cas fetch failed)
    is up to 16 GiB or a directory of many files to unlink."""
    author = authorship_of(request)
    jobs = _jobs(request)
    kind = media_type(request)
    if kind not in (JSON, "application/octet-stream", ""):
        raise UnsupportedMediaType(
            "send application/json with a cid, or the bag as application/octet-stream",
            details={"header": "Content-Type", "received": request.headers.get("content-type")},
        )
    cid = parse_cid((await _named_bag(request)).cid, "cid") if kind == JSON else None
    source = f"cid:{cid}" if cid is not None else f"upload:{author.content_sha256}"
    job = await anyio.to_thread.run_sync(lambda: jobs.unfinished(author.signer, source))
    if job is None:
        await anyio.to_thread.run_sync(lambda: jobs.admit(author.signer))
        async with entered_in_worker_thread(jobs.incoming()) as spool:
            bag, source = await _received_bag(request, spool, cid)
            job = await anyio.to_thread.run_sync(lambda: jobs.submit(bag, source, author))
    return JSONResponse(job.to_json(), status_code=202, headers={"Location": f"/v1/jobs/{job.id}"})


async def _received_bag(request: Request, spool: Path, cid: CID | None) -> tuple[Path, str]:
    """The bag in ``spool``, fetched from cas by ``cid`` or else streamed in, and its name
    as its job keeps it (``cid:`` or ``upload:`` and the digest of what arrived)."""
    settings = request.app.state.settings
    if cid is None:
        return await _spool_upload(request, spool, settings.storage_max_bag_bytes)
    cas = request.app.state.ingest_cas()
    bounds = BagBounds(settings.storage_max_bag_bytes, settings.storage_max_bag_entries)
    bag = await anyio.to_thread.run_sync(lambda: fetch_bag(cas, cid, spool, bounds))
    return bag, f"cid:{cid}"


@router.get("/v1/jobs/{job_id}")
async def get_job(
    request: Request,
    job_id: str,
    after_ns: int | None = Query(
        default=None,
        ge=0,
        le=MAX_UPDATED_NS,
        description="with `wait_s`: the job's `updated_ns` as last read",
    ),
    wait_s: float = wait_parameter("wait up to this long for the job to change past `after_ns`"),
) -> dict[str, Any]:
    """An ingest job: status, messages done of total, topics and what became of them. With
    ``wait_s`` and ``after_ns``, a long poll: the answer comes as soon as the job changes
    (its ``updated_ns`` passes ``after_ns``) or when it is finished, else after ``wait_s``
    as it is (at once while too many others wait, or once the node stops)."""
    jobs = _jobs(request)
    if wait_s:
        if after_ns is None:
            raise Unprocessable(
                "wait_s needs after_ns, the job's updated_ns as last read",
                details={
                    "errors": [{"field": "query.after_ns", "message": "required with wait_s"}]
                },
            )
        seen_ns = after_ns

        async def peek() -> tuple[int, str]:
            return jobs.peek(job_id)

        def changed(seen: tuple[int, str]) -> bool:
            updated_ns, status = seen
            return updated_ns > seen_ns or status in FINISHED

        await long_poll(peek, changed, jobs.changes_of(job_id), wait_s)
    job = await anyio.to_thread.run_sync(jobs.get, job_id)
    return job.to_json()


@router.post("/v1/jobs/{job_id}/resume", status_code=202)
async def resume_job(request: Request, job_id: str) -> dict[str, Any]:
    authorship_of(request)
    job = await anyio.to_thread.run_sync(lambda: _jobs(request).resume(job_id))
    return job.to_json()


@router.get("/v1/bindings")
async def list_bindings(request: Request) -> dict[str, Any]:
    """Every binding. Read on a worker thread: a bind holds their lock across its write."""
    bindings: Bindings = request.app.state.bindings
    return await anyio.to_thread.run_sync(bindings.to_json)


@router.post("/v1/bindings")
async def bind(
    request: Request,
    body: Binding = json_body(Binding),  # type: ignore[assignment]
) -> dict[str, Any]:
    """Bind a topic or a message type to a template id (a topic binding wins)."""
    authorship_of(request)
    bindings: Bindings = request.app.state.bindings
    await anyio.to_thread.run_sync(
        lambda: bindings.bind(template_id=body.template, topic=body.topic, msgtype=body.msgtype)
    )
    return await anyio.to_thread.run_sync(bindings.to_json)


def _encoded_pages(
    engine: QueryEngine, filters: RecordFilters, first: Page, limit: int, encoder: Encoder
) -> Iterator[bytes]:
    """The export's bytes, one query page read and encoded per item (the first page was
    read already), the last item closing the file.

    Each item is one turn of a query slot, so a turn scans what one ``GET /v1/records`` page
    may (``MAX_SCANNED`` documents). Pulling records until an encoded chunk filled read as
    many pages as that took in one turn: an export for a robot with no records scanned the
    whole template without giving its turn back."""
    page, sent = first, 0
    while True:
        records = [stored.record for stored in page.records[: limit - sent]]
        sent += len(records)
        encoded = encoder.add(records)
        if page.next is None or sent == limit:
            yield encoded + encoder.finish()
            return
        yield encoded
        page = engine.records(filters.query(EXPORT_PAGE, page.next))


async def _in_query_slots(chunks: Iterator[bytes], slots: Slots) -> AsyncIterator[bytes]:
    """Pull a blocking generator off the event loop, each chunk (a page read, encoded) in a
    query slot as ``GET /v1/records`` takes; an export that finds none in time breaks off,
    which the client sees as a cut stream, never as a shorter complete one. A page that
    completed no bytes sends nothing."""
    done = object()
    while True:
        chunk = await slots.run_sync(lambda: next(chunks, done))
        if chunk is done:
            return
        assert isinstance(chunk, bytes)
        if chunk:
            yield chunk


@router.get("/v1/export")
async def export(
    request: Request,
    filters: Annotated[RecordFilters, Depends()],
    format: Literal["mcap", "jsonl"] = "jsonl",
    limit: Annotated[int, Query(ge=1, le=10_000_000)] = 1_000_000,
) -> StreamingResponse:
    """A query's records (filters as ``GET /v1/records``) as MCAP or JSON lines, streamed.

    Each export holds a page of records and its encoding while its client takes them (8 MiB
    for pages of 40-float records), so exports stream in turns (``storage_max_exports``), as
    the cas's streams do: a hundred clients that asked for an export and never read took
    the service from 145 to 953 MiB, which it kept after they left."""
    query = filters.query(EXPORT_PAGE)
    engine: QueryEngine = request.app.state.queries
    media, name = EXPORT_FORMATS[format]

    async def open_body() -> AsyncIterator[bytes]:
        first = await in_query_slot(request, lambda: engine.records(query))
        encoder: Encoder
        if format == "mcap":
            catalog = request.app.state.catalog
            encoder = McapEncoder(lambda template_id: catalog.get(template_id).template)
        else:
            encoder = JsonLinesEncoder()
        chunks = _encoded_pages(engine, filters, first, limit, encoder)
        return _in_query_slots(chunks, request.app.state.query_slots)

    return await stream_in_turn(
        request.app.state.export_slots,
        open_body,
        media_type=media,
        headers={"Content-Disposition": f'attachment; filename="{name}"'},
    )
