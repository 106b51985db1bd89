"""Routes of the storage service, and the wiring of its node (logs, epochs, anchoring).

Each engineer's routes sit in their own router function; ``build_app`` includes them all.
"""

from __future__ import annotations

import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import anyio
from fastapi import APIRouter, FastAPI, Request

import services.storage
from robocloud.cas import Cas
from robocloud.ledger import Ledger
from robocloud.proofs import RecordId
from services.common.app import create_app
from services.common.errors import BadRequest
from services.storage import identity
from services.storage.anchoring import LedgerAndCas, StorageNode
from services.storage.errors import ERRORS
from services.storage.settings import StorageSettings

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


def build_app(settings: StorageSettings) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        node: StorageNode = app.state.node
        node.start()
        try:
            yield
        finally:
            await anyio.to_thread.run_sync(node.close)

    app = create_app(
        "storage",
        settings,
        routers=[_proof_router()],
        lifespan=lifespan,
        errors=ERRORS,
        description=services.storage.__doc__ or "",
    )
    app.state.node = _open_node(settings)
    return app
