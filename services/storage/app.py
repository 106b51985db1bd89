"""Routes of the storage service, and the wiring of its node (logs, epochs, anchoring).

Each engineer's routes sit in their own router function; ``build_app`` includes them all.
"""

from __future__ import annotations

import re
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager, contextmanager
from typing import Any
from urllib.parse import parse_qsl

import anyio
from fastapi import APIRouter, FastAPI, Query, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

import services.storage
from robocloud.cas import Cas
from robocloud.ledger import Ledger, LedgerService
from robocloud.proofs import RecordId
from services.common.app import create_app
from services.common.auth import SignedAddress
from services.common.bodies import media_type, read_json
from services.common.errors import BadRequest, UnsupportedMediaType
from services.common.slots import Slots
from services.storage import bags_api, identity, records_api
from services.storage.anchoring import LedgerAndCas, StorageNode
from services.storage.catalog import Catalog
from services.storage.datasets import DatasetPublisher
from services.storage.errors import ERRORS
from services.storage.ingest import IngestJobs
from services.storage.knowledge import KnowledgeBase
from services.storage.matcher import Bindings
from services.storage.queries import QueryEngine
from services.storage.recordstore import Offload, RecordStore, collect_garbage_less_often
from services.storage.settings import StorageSettings
from services.storage.sparql import QueryTooLargeError, SparqlWorkers, UpdateRejectedError
from services.storage.staging import CasBlobs

_COUNT = re.compile(r"0|[1-9][0-9]{0,18}")


def _count(value: str | None, field: str) -> int:
    """A query or path integer in [0, 10**19), else 400 naming ``field``."""
    if value is None:
        raise BadRequest(f"{field} is required", code="missing_parameter", details={"field": field})
    if not _COUNT.fullmatch(value):
        raise BadRequest(
            f"{field} must be a non-negative decimal integer",
            code="invalid_parameter",
            details={"field": field, "value": value[:100]},
        )
    return int(value)


def _node(request: Request) -> StorageNode:
    node: StorageNode = request.app.state.node
    return node


# ----- node, proofs, consistency and epochs (engineer anchor) -----


def _proof_router() -> APIRouter:
    router = APIRouter(tags=["proofs"])

    @router.get("/v1/node")
    async def node_identity(request: Request) -> dict[str, Any]:
        """The node's address (what the ledger grants ``storage_node``) and anchoring state."""
        return await anyio.to_thread.run_sync(_node(request).describe)

    @router.get("/v1/records/{record_id}/proof")
    async def record_proof(request: Request, record_id: str) -> dict[str, Any]:
        """The record with its inclusion proofs and on-chain anchor (409 until anchored)."""
        parsed = RecordId.parse(record_id)
        return await anyio.to_thread.run_sync(_node(request).proofs.record_proof, parsed)

    @router.get("/v1/templates/{template_id}/consistency")
    async def consistency(
        request: Request, template_id: str, first: str | None = None, second: str | None = None
    ) -> dict[str, Any]:
        """An RFC 6962 consistency proof between two sizes of a template's log."""
        first_size, second_size = _count(first, "first"), _count(second, "second")
        proofs = _node(request).proofs
        return await anyio.to_thread.run_sync(
            proofs.consistency, template_id, first_size, second_size
        )

    @router.get("/v1/epochs/{epoch}")
    async def epoch(request: Request, epoch: str) -> dict[str, Any]:
        """An epoch's manifest (sorted template heads, TMT root), its cas CID and anchor."""
        number = _count(epoch, "epoch")
        return await anyio.to_thread.run_sync(_node(request).proofs.epoch, number)

    return router


# ----- knowledge base (engineer semantic) -----

SPARQL_PATH = "/v1/knowledge/sparql"
"""A read: unsigned for POST too, so that any SPARQL 1.1 Protocol client can ask."""


class KnowledgeRequest(BaseModel):
    cid: str = Field(description="the CID of a description in canonical form, stored in cas")


def _knowledge(request: Request) -> KnowledgeBase:
    knowledge: KnowledgeBase = request.app.state.knowledge
    return knowledge


def _sparql_answer(media: str, body: bytes) -> Response:
    charset = "" if media.endswith("+xml") or media.endswith("/xml") else "; charset=utf-8"
    return Response(body, media_type=f"{media}{charset}", headers={"Vary": "Accept"})


def _knowledge_router(settings: StorageSettings) -> APIRouter:
    router = APIRouter(tags=["knowledge"])
    # One turn per worker process: a query waiting for a free worker waits on the event loop,
    # not on one of the threads every other route needs.
    worker_turns = Slots("SPARQL", settings.knowledge_workers, settings.knowledge_query_timeout_s)

    async def run_query(
        request: Request, query: str | None, update: str | None, format_hint: str | None
    ) -> Response:
        if update is not None:
            raise UpdateRejectedError("this endpoint answers queries only: updates are rejected")
        if query is None:
            raise BadRequest(
                "the query parameter is required",
                code="missing_parameter",
                details={"field": "query"},
            )
        size = len(query.encode())
        if size > settings.knowledge_max_query_bytes:
            raise QueryTooLargeError(size, settings.knowledge_max_query_bytes)
        accept = request.headers.get("accept")
        workers = _knowledge(request).workers
        media, body = await worker_turns.run_sync(lambda: workers.query(query, accept, format_hint))
        return _sparql_answer(media, body)

    def dataset_refused(parameters: list[tuple[str, str]]) -> None:
        for name, _ in parameters:
            if name in ("default-graph-uri", "named-graph-uri", "using-graph-uri"):
                raise BadRequest(
                    f"{name} is not supported: the knowledge base is one graph",
                    code="unsupported_parameter",
                    details={"field": name},
                )

    def one(parameters: list[tuple[str, str]], name: str) -> str | None:
        values = [value for key, value in parameters if key == name]
        if len(values) > 1:
            raise BadRequest(
                f"{name} is given {len(values)} times",
                code="invalid_parameter",
                details={"field": name},
            )
        return values[0] if values else None

    def format_hint(parameters: list[tuple[str, str]]) -> str | None:
        return one(parameters, "format") or one(parameters, "output")

    @router.post("/v1/knowledge")
    async def add_description(request: Request, signer: SignedAddress) -> dict[str, Any]:
        """Fetch a description from cas by CID, validate it against its shapes and index it."""
        body = await read_json(request, KnowledgeRequest)
        assert body is not None
        indexed = await anyio.to_thread.run_sync(_knowledge(request).add, body.cid)
        return indexed.as_dict()

    @router.get("/v1/knowledge")
    async def knowledge_state(request: Request) -> dict[str, Any]:
        """How many descriptions are indexed, and where the ledger follower is."""
        knowledge = _knowledge(request)
        return {
            "descriptions": len(knowledge),
            "store": settings.knowledge_store,
            "workers": knowledge.workers.describe(),
            "ledger": knowledge.follow_state(),
        }

    @router.get(SPARQL_PATH)
    async def sparql_get(request: Request) -> Response:
        """SPARQL 1.1 Protocol query via GET (``?query=``); answers by content negotiation."""
        parameters = list(request.query_params.multi_items())
        dataset_refused(parameters)
        return await run_query(
            request, one(parameters, "query"), one(parameters, "update"), format_hint(parameters)
        )

    @router.post(SPARQL_PATH)
    async def sparql_post(request: Request) -> Response:
        """SPARQL 1.1 Protocol query via POST: a form (``query=``) or ``application/sparql-query``.

        Updates (``update=`` or ``application/sparql-update``) are rejected.
        """
        kind = media_type(request)
        raw = await request.body()
        parameters = list(request.query_params.multi_items())
        if kind == "application/sparql-update":
            raise UpdateRejectedError("this endpoint answers queries only: updates are rejected")
        if kind == "application/sparql-query":
            query: str | None = raw.decode("utf-8", errors="replace")
        elif kind == "application/x-www-form-urlencoded":
            parameters += _form_fields(raw)
            query = one(parameters, "query")
        else:
            raise UnsupportedMediaType(
                "a SPARQL query is sent as application/x-www-form-urlencoded or "
                "application/sparql-query",
                details={"header": "Content-Type", "received": kind},
            )
        dataset_refused(parameters)
        return await run_query(request, query, one(parameters, "update"), format_hint(parameters))

    @router.get("/v1/knowledge/applications")
    async def applications(
        request: Request,
        consumes: str = Query(
            description="a media type (image/jpeg), its IANA IRI, or a template's ipfs://<cid>"
        ),
        produces: str | None = Query(default=None, description="the same, for an output"),
        limit: int = Query(default=100, ge=1, le=1000),
    ) -> dict[str, Any]:
        """Applications with an input of type ``consumes`` (and an output of ``produces``)."""
        knowledge = _knowledge(request)
        found = await worker_turns.run_sync(
            lambda: knowledge.applications(consumes, produces, limit)
        )
        return {"applications": found}

    return router


MAX_FORM_FIELDS = 32
"""Fields a SPARQL query form may hold: the protocol names a handful (query, format or
output, the graph URIs, which are refused), so this leaves room and bounds the parse."""


def _form_fields(raw: bytes) -> list[tuple[str, str]]:
    """A form body's fields; past :data:`MAX_FORM_FIELDS`, 400 ``invalid_parameter`` naming
    how many it holds: ``parse_qsl`` raises ValueError there, which answered 500."""
    text = raw.decode("utf-8", errors="replace")
    try:
        return parse_qsl(text, max_num_fields=MAX_FORM_FIELDS)
    except ValueError:
        fields = text.count("&") + 1  # as parse_qsl counts them
        raise BadRequest(
            f"the form holds {fields} fields, more than the {MAX_FORM_FIELDS} it may",
            code="invalid_parameter",
            details={"field": "body", "fields": fields, "limit": MAX_FORM_FIELDS},
        ) from None


def _open_knowledge(settings: StorageSettings) -> KnowledgeBase:
    root = settings.resolved_data_dir() / "knowledge"
    workers = SparqlWorkers(
        root / "descriptions",
        workers=settings.knowledge_workers,
        timeout_s=settings.knowledge_query_timeout_s,
        max_result_bytes=settings.knowledge_max_result_bytes,
        memory_bytes=settings.knowledge_worker_memory_bytes,
        store=settings.knowledge_store,
    )

    @contextmanager
    def connect_cas() -> Iterator[Cas]:
        with Cas(settings.cas_url) as cas:
            yield cas

    return KnowledgeBase(root, workers, connect_cas)


@asynccontextmanager
async def _knowledge_running(app: FastAPI, settings: StorageSettings) -> AsyncIterator[None]:
    knowledge: KnowledgeBase = app.state.knowledge
    knowledge.workers.start()
    if settings.knowledge_follow_ledger:

        @contextmanager
        def connect_ledger() -> Iterator[LedgerService]:
            with LedgerService(settings.ledger_url) as ledger:
                yield ledger

        knowledge.follow(connect_ledger, settings.knowledge_poll_s)
    try:
        yield
    finally:
        await anyio.to_thread.run_sync(knowledge.close)
        await anyio.to_thread.run_sync(knowledge.workers.close)


def _open_node(settings: StorageSettings) -> StorageNode:
    data_dir = settings.resolved_data_dir()
    node_identity = identity.NodeIdentity(
        identity.load_or_create(data_dir, settings.node_passphrase())
    )

    def connect() -> LedgerAndCas:
        ledger = Ledger.connect(settings.ledger_url, node_identity.identity)
        return LedgerAndCas(ledger, Cas(settings.cas_url, node_identity.identity))

    return StorageNode(
        data_dir,
        node_identity,
        connect,
        anchor=settings.storage_anchor,
        epoch_s=settings.storage_epoch_s,
        epoch_records=settings.storage_epoch_records,
        retry_s=settings.storage_anchor_retry_s,
        register=settings.storage_register,
    )


# ----- templates, records and queries (engineer records) -----
def _cas_offload(node: StorageNode, settings: StorageSettings) -> Offload:
    """Large arrays go to cas signed by the node's own key, the one the ledger registered."""
    clients: dict[str, Cas] = {}

    def offload(data: bytes) -> str:
        if "cas" not in clients:
            clients["cas"] = Cas(settings.cas_url, node.identity.identity, retries=1)
        return str(clients["cas"].add_bytes(data))

    return offload


def _open_records(app: FastAPI, settings: StorageSettings, node: StorageNode) -> None:
    collect_garbage_less_often()
    data_dir = settings.resolved_data_dir()
    app.state.catalog = Catalog(
        data_dir / "catalog",
        max_versions=settings.storage_max_templates,
        max_bytes=settings.storage_max_template_bytes,
    )
    app.state.record_logs = node.logs
    app.state.records = RecordStore(
        data_dir,
        node.logs,
        app.state.catalog,
        segment_records=settings.storage_segment_records,
        segment_cache=settings.storage_segment_cache,
        array_inline_bytes=settings.storage_array_inline_bytes,
        offload=_cas_offload(node, settings),
        notify=node.notify,
    )
    app.state.queries = QueryEngine(app.state.records)
    app.state.query_slots = Slots(
        "query", settings.storage_max_queries, settings.storage_query_wait_s
    )
    app.state.export_slots = Slots(
        "export", settings.storage_max_exports, settings.storage_query_wait_s
    )


def _close_records(app: FastAPI) -> None:
    app.state.records.close()
    app.state.catalog.close()


# ----- bag ingestion and export (engineer bags) -----
def _open_ingest(
    app: FastAPI, settings: StorageSettings, node: StorageNode, knowledge: KnowledgeBase
) -> None:
    data_dir = settings.resolved_data_dir()
    offload = _cas_offload(node, settings)
    clients: dict[str, Cas] = {}

    def cas() -> Cas:
        if "cas" not in clients:
            clients["cas"] = Cas(settings.cas_url, node.identity.identity, retries=1)
        return clients["cas"]

    @contextmanager
    def ledger() -> Iterator[Ledger]:
        with Ledger.connect(settings.ledger_url, node.identity.identity) as chain:
            yield chain

    publish = DatasetPublisher(
        app.state.records,
        knowledge,
        cas,
        ledger,
        node.identity,
        epochs=node.epochs if node.anchorer is not None else None,
        epoch_wait_s=2 * settings.storage_epoch_s + 1,
    )
    app.state.ingest_cas = cas
    app.state.bindings = Bindings(data_dir / "bindings.json")
    app.state.ingest_jobs = IngestJobs(
        data_dir / "ingest",
        app.state.records,
        app.state.record_logs,
        app.state.bindings,
        lambda: CasBlobs(offload),
        batch_records=settings.storage_ingest_batch_records,
        staging_workers=settings.storage_ingest_workers,
        parallel_from_messages=settings.storage_ingest_parallel_messages,
        worker_memory_bytes=settings.storage_ingest_worker_memory_bytes,
        stall_s=settings.storage_ingest_stall_s,
        max_pending=settings.storage_max_ingest_jobs,
        publish=publish if settings.storage_publish_datasets else None,
    )


def build_app(settings: StorageSettings) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        node: StorageNode = app.state.node
        node.start()
        try:
            async with _knowledge_running(app, settings):
                yield
        finally:
            await anyio.to_thread.run_sync(app.state.ingest_jobs.close)
            await anyio.to_thread.run_sync(_close_records, app)
            await anyio.to_thread.run_sync(node.close)

    async def knowledge_loaded() -> None:
        """Ready once a SPARQL worker has loaded the graph and warmed rdflib's parser."""
        if not app.state.knowledge.workers.loaded():
            raise RuntimeError("the knowledge base's query workers are still starting")

    app = create_app(
        "storage",
        settings,
        routers=[_proof_router(), records_api.router, bags_api.router, _knowledge_router(settings)],
        readiness_checks=[knowledge_loaded],
        unsigned_paths=[SPARQL_PATH],
        lifespan=lifespan,
        body_limits={
            "/v1/templates": records_api.TEMPLATE_BODY_LIMIT,
            "/v1/records": settings.storage_max_batch_bytes,
            "/v1/ingest": settings.storage_max_bag_bytes,
        },
        errors=ERRORS,
        description=services.storage.__doc__ or "",
    )
    app.state.node = _open_node(settings)
    _open_records(app, settings, app.state.node)
    app.state.knowledge = _open_knowledge(settings)
    _open_ingest(app, settings, app.state.node, app.state.knowledge)
    return app
