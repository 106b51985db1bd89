"""Routes of the storage service, and the wiring of its node (logs, epochs, anchoring).

Each engineer's routes sit in their own module (``records_api``, ``bags_api``,
``knowledge_api``) or router function; ``build_app`` includes them all.
"""

from __future__ import annotations

import re
from collections.abc import AsyncIterator, Iterator, Sequence
from contextlib import asynccontextmanager, contextmanager
from typing import Any

import anyio
from fastapi import APIRouter, FastAPI, Request

import services.storage
from robocloud.cas import Cas
from robocloud.ledger import Ledger
from robocloud.proofs import RecordId
from services.common.app import create_app
from services.common.bodies import SMALL_JSON_BODY
from services.common.errors import BadRequest
from services.common.slots import Slots
from services.storage import bags_api, identity, knowledge_api, records_api
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
from services.storage.staging import CasBlobs

_COUNT = re.compile(r"0|[1-9][0-9]{0,18}")
STORING_PATHS = ("/v1/records", "/v1/ingest", "/v1/jobs/", "/v1/knowledge")
"""The writes that bring data (records, bags, a job's commit run again, descriptions): they
leave the disk's reserve free. Templates and bindings are a few fields each and pass."""


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


def _open_node(settings: StorageSettings) -> StorageNode:
    data_dir = settings.resolved_data_dir()
    node_identity = identity.NodeIdentity(
        identity.load_or_create(data_dir, settings.node_passphrase())
    )

    def connect() -> LedgerAndCas:
        ledger = Ledger.connect(
            settings.ledger_url,
            node_identity.identity,
            receipt_timeout_s=settings.storage_receipt_timeout_s,
        )
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

    def offload(blobs: Sequence[bytes]) -> list[str]:
        if "cas" not in clients:
            clients["cas"] = Cas(settings.cas_url, node.identity.identity, retries=1)
        return [str(cid) for cid in clients["cas"].add_blobs(blobs)]

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
    clients: dict[str, Cas] = {}

    def cas() -> Cas:
        if "cas" not in clients:
            clients["cas"] = Cas(settings.cas_url, node.identity.identity, retries=1)
        return clients["cas"]

    @contextmanager
    def ledger() -> Iterator[Ledger]:
        with Ledger.connect(
            settings.ledger_url,
            node.identity.identity,
            receipt_timeout_s=settings.storage_receipt_timeout_s,
        ) as chain:
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
        lambda: CasBlobs(lambda blobs: [str(cid) for cid in cas().add_blobs(blobs)]).put_many,
        batch_records=settings.storage_ingest_batch_records,
        staging_workers=settings.storage_ingest_workers,
        parallel_from_messages=settings.storage_ingest_parallel_messages,
        worker_memory_bytes=settings.storage_ingest_worker_memory_bytes,
        stall_s=settings.storage_ingest_stall_s,
        max_pending=settings.storage_max_ingest_jobs,
        max_pending_per_robot=settings.storage_max_ingest_jobs_per_robot,
        publish=publish if settings.storage_publish_datasets else None,
        publish_attempts=settings.storage_publish_attempts,
        publish_retry_s=settings.storage_publish_retry_s,
        keep_resumable_s=settings.storage_keep_resumable_s,
        disk_reserve=app.state.disk_reserve,
    )
    app.state.on_stop.append(app.state.ingest_jobs.stop_waits)


def build_app(settings: StorageSettings) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        node: StorageNode = app.state.node
        node.start()
        try:
            async with knowledge_api.knowledge_running(app, settings):
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
        routers=[
            _proof_router(),
            records_api.router,
            bags_api.router,
            knowledge_api.knowledge_router(settings),
        ],
        readiness_checks=[knowledge_loaded],
        unsigned_paths=[knowledge_api.SPARQL_PATH],
        lifespan=lifespan,
        body_limits={
            "/v1/templates": records_api.TEMPLATE_BODY_LIMIT,
            "/v1/records": settings.storage_max_batch_bytes,
            "/v1/ingest": settings.storage_max_bag_bytes,
            "/v1/knowledge": SMALL_JSON_BODY,
            knowledge_api.SPARQL_PATH: knowledge_api.sparql_body_limit(settings),
        },
        storing_paths=STORING_PATHS,
        errors=ERRORS,
        description=services.storage.__doc__ or "",
    )
    app.state.node = _open_node(settings)
    _open_records(app, settings, app.state.node)
    app.state.knowledge = knowledge_api.open_knowledge(settings)
    _open_ingest(app, settings, app.state.node, app.state.knowledge)
    return app
