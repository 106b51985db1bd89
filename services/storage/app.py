"""Routes of the storage service and the wiring of its parts."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

import services.storage
from robocloud.cas import Cas
from robocloud.identity import Identity
from services.common.app import create_app
from services.storage import bags_api, records_api
from services.storage.catalog import Catalog
from services.storage.errors import ERRORS
from services.storage.ingest import CasBlobs, IngestJobs
from services.storage.matcher import Bindings
from services.storage.queries import QueryEngine
from services.storage.recordlog import RecordLogs
from services.storage.recordstore import Offload, RecordStore
from services.storage.settings import StorageSettings


# ----- templates, records and queries (engineer records) -----
def _cas_offload(app: FastAPI, settings: StorageSettings) -> Offload:
    """Large arrays go to cas signed by the node's key (``app.state.node_identity``).

    A node without its own identity wired yet signs with a key made for this process, which a
    cas in ``signed`` mode accepts and one in ``registered`` mode refuses (502, nothing stored).
    """
    clients: dict[str, Cas] = {}

    def offload(data: bytes) -> str:
        if "cas" not in clients:
            identity = getattr(app.state, "node_identity", None) or Identity.generate()
            clients["cas"] = Cas(settings.cas_url, identity, retries=1)
        return str(clients["cas"].add_bytes(data))

    return offload


def _open_records(app: FastAPI, settings: StorageSettings) -> None:
    data_dir = settings.resolved_data_dir()
    app.state.catalog = Catalog(data_dir / "catalog", max_versions=settings.storage_max_templates)
    app.state.record_logs = RecordLogs(data_dir / "logs")
    app.state.records = RecordStore(
        data_dir,
        app.state.record_logs,
        app.state.catalog,
        segment_records=settings.storage_segment_records,
        segment_cache=settings.storage_segment_cache,
        array_inline_bytes=settings.storage_array_inline_bytes,
        offload=_cas_offload(app, settings),
        notify=getattr(app.state, "node_notify", None),
    )
    app.state.queries = QueryEngine(app.state.records)


def _close_records(app: FastAPI) -> None:
    app.state.records.close()
    app.state.record_logs.close()
    app.state.catalog.close()


# ----- bag ingestion and export (engineer bags) -----
def _open_ingest(app: FastAPI, settings: StorageSettings) -> None:
    data_dir = settings.resolved_data_dir()
    offload = _cas_offload(app, settings)
    clients: dict[str, Cas] = {}

    def cas() -> Cas:
        if "cas" not in clients:
            identity = getattr(app.state, "node_identity", None) or Identity.generate()
            clients["cas"] = Cas(settings.cas_url, identity, retries=1)
        return clients["cas"]

    app.state.ingest_cas = cas
    app.state.bindings = Bindings(data_dir / "bindings.json")
    app.state.ingest_jobs = IngestJobs(
        data_dir / "ingest",
        app.state.records,
        app.state.record_logs,
        app.state.bindings,
        lambda: CasBlobs(offload),
        batch_records=settings.storage_ingest_batch_records,
        max_pending=settings.storage_max_ingest_jobs,
    )


def build_app(settings: StorageSettings) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        try:
            yield
        finally:
            app.state.ingest_jobs.close()
            _close_records(app)

    app = create_app(
        "storage",
        settings,
        routers=[records_api.router, bags_api.router],
        lifespan=lifespan,
        body_limits={
            "/v1/templates": records_api.TEMPLATE_BODY_LIMIT,
            "/v1/records": settings.storage_max_batch_bytes,
            "/v1/ingest": settings.storage_max_bag_bytes,
        },
        errors=ERRORS,
        description=services.storage.__doc__ or "",
    )
    _open_records(app, settings)
    _open_ingest(app, settings)
    return app
