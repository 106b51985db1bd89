"""Routes of the ledger service: JSON-RPC at ``/rpc``, REST reads, the development faucet.

``/rpc`` is unsigned at the HTTP layer: every transaction carries its sender's Ethereum
signature, and reads are public. The faucet is signed and funds only its signer. Any valid
signature may use it: a robot asks the faucet before it can register, so the ledger cannot
require registration (it runs with ``AnySigner`` whatever ``ROBOCLOUD_AUTH`` says).
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from functools import partial
from typing import Any

import anyio
from fastapi import APIRouter, FastAPI, Query, Request
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field

import services.ledger
from robocloud.ledger import ContractAddresses
from robocloud.signing import chain_deployment_id
from services.common.app import create_app
from services.common.auth import SignedAddress
from services.common.bodies import SMALL_JSON_BODY, read_json, wait_parameter
from services.common.changes import long_poll
from services.common.errors import Forbidden, Unavailable
from services.common.slots import Slots
from services.ledger import views
from services.ledger.backend import open_ledger
from services.ledger.endpoint import RpcEndpoint
from services.ledger.errors import ERRORS
from services.ledger.forwarding import NodeForwarder
from services.ledger.grants import RoleGrant, open_granter
from services.ledger.node import Ledger
from services.ledger.rpc import EncodedBatch
from services.ledger.settings import LedgerSettings

log = logging.getLogger("robocloud.ledger")

READY_TIMEOUT_S = 2.0
UINT64_MAX = 2**64 - 1
"""Block numbers and epochs are uint64 on chain; beyond, a query is refused (422) by name."""


class FaucetRequest(BaseModel):
    address: str = Field(max_length=64)


async def _read(view: Callable[..., dict[str, Any]], *args: Any) -> dict[str, Any]:
    """A view of the event index, on a worker thread: its SQLite queries (a scan of every
    anchor unfiltered) and the index's lock, held while a block is indexed, kept the event
    loop and every other request waiting."""
    return await anyio.to_thread.run_sync(lambda: view(*args))


def _ledger(request: Request) -> Ledger:
    ledger: Ledger | None = getattr(request.app.state, "ledger", None)
    if ledger is None:
        raise Unavailable("the ledger is starting")
    return ledger


def _rpc(request: Request) -> RpcEndpoint:
    endpoint: RpcEndpoint | None = getattr(request.app.state, "rpc", None)
    if endpoint is None:
        raise Unavailable("the ledger is starting")
    return endpoint


def _router() -> APIRouter:
    router = APIRouter(tags=["ledger"])

    @router.post("/rpc")
    async def rpc(request: Request) -> Response:
        """Ethereum JSON-RPC 2.0: single calls and batches."""
        endpoint = _rpc(request)
        answer = await endpoint.answer(await request.body())
        if answer is None:
            return Response(status_code=204)
        if isinstance(answer, EncodedBatch):
            return Response(answer.body(), media_type="application/json")
        return JSONResponse(answer)

    @router.get("/v1/contracts")
    async def contracts(request: Request) -> dict[str, Any]:
        """Where Registry and AnchorLog are deployed, with their ABIs."""
        ledger = _ledger(request)
        return ledger.deployment.describe(ledger.chain_id)

    @router.get("/v1/robots/{address}")
    async def robot(request: Request, address: str) -> dict[str, Any]:
        """A robot: status (registered or pending), metadata CID, activity, roles (indexed)."""
        return await _read(views.robot, _ledger(request), address)

    @router.get("/v1/registrations")
    async def registrations(request: Request, limit: int = 100) -> dict[str, Any]:
        """Registrations awaiting the admin or a registrar (the Approved mode), oldest first."""
        return await _read(views.pending_registrations, _ledger(request), limit)

    @router.get("/v1/advertisements")
    async def advertisements(
        request: Request,
        cid: str | None = None,
        advertiser: str | None = None,
        since: int = Query(default=0, ge=0, le=UINT64_MAX, description="first block number"),
        limit: int = 100,
        after_log_index: int | None = Query(
            default=None,
            ge=0,
            le=UINT64_MAX,
            description="block `since`'s events only past this log index (a saved position)",
        ),
        wait_s: float = wait_parameter(
            "when there are none yet, wait up to this long for a block bringing one"
        ),
    ) -> dict[str, Any]:
        """Advertised events, oldest first, by CID and/or advertiser. With ``wait_s``, a
        long poll: the answer comes as soon as a new block holds one, else after ``wait_s``
        with none (at once while too many others wait, or once the ledger stops)."""
        ledger = _ledger(request)
        read = partial(
            _read, views.advertisements, ledger, cid, advertiser, since, limit, after_log_index
        )
        return await long_poll(
            read, lambda answer: bool(answer["advertisements"]), ledger.index.changes, wait_s
        )

    @router.get("/v1/anchors")
    async def anchors(
        request: Request,
        node: str | None = None,
        epoch: int | None = Query(default=None, ge=0, le=UINT64_MAX),
        limit: int = 100,
    ) -> dict[str, Any]:
        """Anchored TMT roots by storage node and/or epoch."""
        return await _read(views.anchors, _ledger(request), node, epoch, limit)

    @router.get("/v1/blocks/latest")
    async def latest_block(request: Request) -> dict[str, Any]:
        ledger = _ledger(request)
        return await anyio.to_thread.run_sync(ledger.latest_block)

    @router.post("/v1/faucet")
    async def faucet(request: Request, signer: SignedAddress) -> dict[str, Any]:
        """Fund the signer on the development chain (rate-limited)."""
        ledger = _ledger(request)
        body = await read_json(request, FaucetRequest)
        assert body is not None
        address = views.address_param(body.address, "address")
        if address != signer:
            raise Forbidden(
                f"the faucet funds only its signer {signer}, not {address}",
                code="faucet_signer_mismatch",
                details={"address": address, "signer": signer},
            )
        return await anyio.to_thread.run_sync(ledger.fund, address)

    return router


async def _grant_roles(ledger: Ledger, settings: LedgerSettings, grants: list[RoleGrant]) -> None:
    """Apply the configured role grants, retrying until each is done (see ``grants``)."""
    granter = await anyio.to_thread.run_sync(
        open_granter,
        ledger.dispatcher.handle,
        ContractAddresses(ledger.deployment.registry, ledger.deployment.anchor_log),
        settings.resolved_data_dir(),
        settings.admin_passphrase(),
        grants,
    )
    if granter is None:
        return
    try:
        while True:
            try:
                if await anyio.to_thread.run_sync(granter.attempt):
                    return
            except Exception as exc:
                log.warning("granting roles failed; retrying", extra={"error": str(exc)})
            await anyio.sleep(settings.ledger_poll_interval_s)
    finally:
        granter.close()


def build_app(settings: LedgerSettings) -> FastAPI:
    grants = settings.role_grants()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        ledger = await anyio.to_thread.run_sync(open_ledger, settings)
        app.state.ledger = ledger
        app.state.on_stop.append(ledger.index.changes.close)
        forwarder = None
        if settings.ledger_rpc_url:
            forwarder = NodeForwarder(
                settings.ledger_rpc_url,
                settings.ledger_rpc_max_forwards,
                settings.ledger_rpc_evm_timeout_s,
            )
        app.state.rpc = RpcEndpoint(
            ledger.dispatcher,
            Slots("call", settings.ledger_rpc_max_calls, settings.ledger_rpc_evm_timeout_s),
            forwarder,
        )
        app.state.audience.learn(chain_deployment_id(ledger.chain_id, ledger.deployment.registry))
        try:
            async with anyio.create_task_group() as tasks:
                background = app.state.background
                follow = getattr(ledger, "follow", None)
                if follow is not None:
                    background.start(tasks, "index", follow)
                if grants:
                    background.start(
                        tasks, "role-grants", partial(_grant_roles, ledger, settings, grants)
                    )
                yield
                tasks.cancel_scope.cancel()
        finally:
            app.state.ledger = None
            app.state.rpc = None
            if forwarder is not None:
                await forwarder.aclose()
            await anyio.to_thread.run_sync(ledger.close)

    async def chain_answers() -> None:
        """Ready only while the chain answers a read within ``READY_TIMEOUT_S``."""
        ledger: Ledger | None = getattr(app.state, "ledger", None)
        if ledger is None:
            raise RuntimeError("the ledger is not open")
        try:
            with anyio.fail_after(READY_TIMEOUT_S):
                await anyio.to_thread.run_sync(ledger.latest_block, abandon_on_cancel=True)
        except TimeoutError:
            raise RuntimeError(f"the chain did not answer within {READY_TIMEOUT_S:g} s") from None

    app = create_app(
        "ledger",
        settings.model_copy(update={"auth": "signed"}),
        routers=[_router()],
        readiness_checks=[chain_answers],
        lifespan=lifespan,
        unsigned_paths=["/rpc"],
        body_limits={"/v1/faucet": min(SMALL_JSON_BODY, settings.max_body_bytes)},
        errors=ERRORS,
        description=services.ledger.__doc__ or "",
        deployment_source="service",
    )
    return app
