"""The cas service: wiring of the store, its metrics and its background garbage collection."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from functools import partial
from pathlib import Path

import anyio
from fastapi import FastAPI
from prometheus_client import Counter

import services.cas
from robocloud.cid import CID
from services.cas import gateway, kubo
from services.cas.errors import ERRORS
from services.cas.settings import CasSettings
from services.cas.store import ContentStore
from services.cas.streams import STREAM_WAIT_S
from services.common.app import create_app
from services.common.slots import Slots

log = logging.getLogger("robocloud.cas")

UPLOAD_PATHS = ("/api/v0/add", "/api/v0/dag/import")
STORING_PATHS = (*UPLOAD_PATHS, "/api/v0/block/put", "/api/v0/pin/add")
"""The writes that bring blocks (``pin/add`` fetches missing ones from peers): they leave the
disk's reserve free. ``pin/rm`` and ``repo/gc`` free space and are never refused for it."""
MAX_BLOCK_PUT_BYTES = 4 * 1024 * 1024


def _open_store(settings: CasSettings, app: FastAPI) -> ContentStore:
    registry = app.state.metrics.registry
    corrupt = Counter(
        "robocloud_cas_corrupt_blocks",
        "Blocks found corrupted on read and quarantined.",
        registry=registry,
    )
    fetches = Counter(
        "robocloud_cas_peer_fetches",
        "Block fetches from peers, by outcome.",
        ["peer", "outcome"],
        registry=registry,
    )

    not_kept = Counter(
        "robocloud_cas_peer_blocks_not_kept",
        "Blocks fetched from peers for reads and served without being kept, past "
        "ROBOCLOUD_CAS_MAX_CACHED_BYTES_PER_HOUR.",
        registry=registry,
    )

    def on_corrupt(cid: CID, quarantined: Path) -> None:
        corrupt.inc()

    def on_outcome(peer: str, outcome: str) -> None:
        fetches.labels(peer, outcome).inc()

    return ContentStore.open(
        settings.resolved_data_dir(),
        settings.cas_peers,
        peer_timeout_s=settings.cas_peer_timeout_s,
        max_cached_bytes_per_hour=settings.cas_max_cached_bytes_per_hour,
        on_corrupt=on_corrupt,
        on_peer_outcome=on_outcome,
        on_not_kept=lambda cid: not_kept.inc(),
    )


async def _collect_periodically(store: ContentStore, settings: CasSettings) -> None:
    """Collect every ``cas_gc_interval_s``; a round that fails (a full disk) is logged and
    the next one tries again, since content keeps arriving and waiting to be collected."""
    while True:
        await anyio.sleep(settings.cas_gc_interval_s)
        try:
            removed = await anyio.to_thread.run_sync(store.collect_garbage, settings.cas_gc_grace_s)
        except Exception:
            log.exception("garbage collection failed; the next round tries again")
            continue
        log.info("garbage collected", extra={"removed_blocks": len(removed)})


def build_app(settings: CasSettings) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        store: ContentStore = app.state.store
        async with anyio.create_task_group() as group:
            if settings.cas_gc_interval_s > 0:
                app.state.background.start(
                    group, "garbage-collection", partial(_collect_periodically, store, settings)
                )
            try:
                yield
            finally:
                group.cancel_scope.cancel()
        store.close()

    async def blockstore_writable() -> None:
        app.state.store.check_writable()

    app = create_app(
        "cas",
        settings,
        routers=[gateway.router, kubo.router],
        readiness_checks=[blockstore_writable],
        lifespan=lifespan,
        unsigned_paths=kubo.READ_PATHS,
        body_limits={
            **{path: settings.cas_max_upload_bytes for path in UPLOAD_PATHS},
            "/api/v0/block/put": MAX_BLOCK_PUT_BYTES,
        },
        storing_paths=STORING_PATHS,
        errors=ERRORS,
        description=services.cas.__doc__ or "",
    )
    app.state.store = _open_store(settings, app)
    app.state.listing_slots = Slots("listing", gateway.LISTING_TURNS, gateway.LISTING_WAIT_S)
    app.state.stream_slots = Slots("stream", settings.cas_max_streams, STREAM_WAIT_S)
    return app
