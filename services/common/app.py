"""The app factory: every service gets the same framework endpoints, errors and guards.

``create_app`` returns a FastAPI app with ``/healthz``, ``/readyz``, ``/metrics``,
``GET /v1/audience``, ``POST /v1/whoami``, OpenAPI docs served without any CDN, the JSON error
model for every error (unknown routes included), and the request guard's layers. A service
adds its routers and readiness checks and keeps its own state on ``app.state``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping, Sequence
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from functools import partial
from typing import Any, Literal

import anyio
from fastapi import APIRouter, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from fastapi_offline import FastAPIOffline
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import BaseRoute, Match
from starlette.types import Scope

import robocloud
from robocloud import bounded_json
from robocloud.signing import LOCAL_DEPLOYMENT
from services.common.audience import ServiceAudience, learn_from_ledger
from services.common.auth import SignedAddress, build_authorizer
from services.common.background import BackgroundTasks
from services.common.bodies import SMALL_JSON_BODY, read_json
from services.common.disk import DiskReserve
from services.common.errors import (
    COMMON_ERRORS,
    ErrorMap,
    ServiceError,
    Unavailable,
    error_body,
)
from services.common.logs import configure_logging, request_id_var
from services.common.metrics import CONTENT_TYPE, ServiceMetrics
from services.common.middleware import (
    AccessLogLayer,
    BodyLimitLayer,
    DiskReserveLayer,
    RequestIdLayer,
    SignatureLayer,
)
from services.common.nonces import NonceStore
from services.common.settings import ServiceSettings

log = logging.getLogger("robocloud.app")

ReadinessCheck = Callable[[], Awaitable[None]]
Lifespan = Callable[[FastAPI], AbstractAsyncContextManager[None]]
DeploymentSource = Literal["settings", "ledger", "service"]

DOCS_ASSETS = "/docs/assets"
"""Where Swagger UI's and ReDoc's scripts and styles are served from, offline."""

_HTTP_CODES = {
    400: "bad_request",
    404: "not_found",
    405: "method_not_allowed",
    413: "payload_too_large",
    415: "unsupported_media_type",
}


class WhoamiRequest(BaseModel):
    """An optional challenge the robot chooses, echoed back to bind the answer to its call."""

    challenge: str | None = Field(default=None, max_length=256)


class AudienceResponse(BaseModel):
    audience: str = Field(description="<service>@<deployment>: what signatures must name")
    service: str
    deployment: str


class WhoamiResponse(BaseModel):
    address: str
    service: str
    auth: str
    challenge: str | None


def _json_error(
    status: int, code: str, message: str, details: dict[str, Any], headers: Mapping[str, str]
) -> JSONResponse:
    """The error answer, whatever text it echoes.

    A message or detail may quote what a client sent; a string holding a lone surrogate
    cannot be encoded as UTF-8, and the error answer would itself fail (a 500 in place of
    the 400). Such characters become U+FFFD, as a decoder does with bytes that are not UTF-8,
    rather than escapes: I-JSON (RFC 7493) forbids lone surrogates even escaped, and
    ``robocloud.bounded_json`` refuses them.
    """
    body = error_body(code, message, details, request_id_var.get())
    try:
        return JSONResponse(body, status_code=status, headers=dict(headers))
    except UnicodeEncodeError:
        text = bounded_json.LONE_SURROGATE.sub("\ufffd", json.dumps(body, ensure_ascii=False))
        return JSONResponse(json.loads(text), status_code=status, headers=dict(headers))


def _install_error_handlers(app: FastAPI, errors: ErrorMap) -> None:
    @app.exception_handler(ServiceError)
    async def service_error(_: Request, exc: ServiceError) -> JSONResponse:
        return _json_error(exc.status, exc.code, exc.message, exc.details, exc.headers)

    async def domain_error(_: Request, exc: Exception) -> JSONResponse:
        error = errors.to_service_error(exc)
        assert error is not None, "registered only for the map's exception types"
        return _json_error(error.status, error.code, error.message, error.details, error.headers)

    for exception_type in errors.rules:
        app.add_exception_handler(exception_type, domain_error)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = _HTTP_CODES.get(exc.status_code, "http_error")
        message = str(exc.detail)
        if exc.status_code == 404:
            message = f"no route {request.method} {request.url.path}"
        return _json_error(exc.status_code, code, message, {}, exc.headers or {})

    @app.exception_handler(RequestValidationError)
    async def validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [
            {
                "field": ".".join(str(part) for part in error["loc"]),
                "message": error["msg"],
                "type": error["type"],
            }
            for error in exc.errors()
        ]
        message = f"invalid request: {errors[0]['field']}: {errors[0]['message']}"
        return _json_error(422, "validation_error", message, {"errors": errors}, {})


def _framework_router(
    service: str, settings: ServiceSettings, audience: ServiceAudience
) -> APIRouter:
    router = APIRouter(tags=["framework"])

    @router.get("/healthz")
    async def healthz() -> dict[str, str]:
        """Liveness: the process serves requests."""
        return {"status": "ok", "service": service, "version": robocloud.__version__}

    @router.get("/readyz")
    async def readyz(request: Request) -> dict[str, str]:
        """Readiness: every dependency the service needs answered its check."""
        failures: dict[str, str] = {}
        for check in request.app.state.readiness_checks:
            try:
                await check()
            except Exception as exc:
                failures[getattr(check, "__name__", "check")] = str(exc)
        if failures:
            raise Unavailable(f"{service} is not ready", details={"checks": failures})
        return {"status": "ready", "service": service, "version": robocloud.__version__}

    @router.get("/metrics", response_class=Response)
    async def metrics(request: Request) -> Response:
        """Prometheus text exposition."""
        return Response(request.app.state.metrics.render(), media_type=CONTENT_TYPE)

    @router.get("/v1/audience", response_model=AudienceResponse)
    async def audience_of_service() -> AudienceResponse:
        """The audience a signed request to this service must name (503 until it is known)."""
        return AudienceResponse.model_validate(audience.require().describe())

    @router.post("/v1/whoami", response_model=WhoamiResponse)
    async def whoami(request: Request, address: SignedAddress) -> WhoamiResponse:
        """Check a signature end to end: answers the address the service verified."""
        body = await read_json(request, WhoamiRequest, optional=True)
        return WhoamiResponse(
            address=address,
            service=service,
            auth=settings.auth,
            challenge=body.challenge if body else None,
        )

    return router


def create_app(
    service: str,
    settings: ServiceSettings,
    *,
    routers: Sequence[APIRouter] = (),
    readiness_checks: Sequence[ReadinessCheck] = (),
    lifespan: Lifespan | None = None,
    unsigned_paths: Sequence[str] = (),
    body_limits: Mapping[str, int] | None = None,
    storing_paths: Sequence[str] = (),
    errors: ErrorMap | None = None,
    description: str = "",
    deployment_source: DeploymentSource | None = None,
) -> FastAPI:
    """Build a service app.

    ``unsigned_paths`` are write routes that carry their own authentication (the chain's
    JSON-RPC, whose transactions are signed by Ethereum keys). ``body_limits`` sets the
    body limit under a path prefix: above ``settings.max_body_bytes`` for uploads, below it
    for routes of a few fields (``/v1/whoami`` has ``SMALL_JSON_BODY``). Writes under a
    prefix in ``storing_paths`` (uploads, records) leave ``settings.disk_reserve_bytes`` of the
    disk free (``DiskReserveLayer``); deletions are never among them. ``errors``
    maps the service's domain exceptions to HTTP errors (see ``services.common.errors``),
    beside ``COMMON_ERRORS`` for the SDK's format errors.

    ``deployment_source`` says where the deployment id in the service's audience comes from:
    ``settings`` (``ROBOCLOUD_DEPLOYMENT_ID``, default ``local``), ``ledger`` (learned from
    ``GET /v1/audience`` of the ledger at ``ROBOCLOUD_LEDGER_URL``; not ready until then), or
    ``service`` (the service calls ``app.state.audience.learn`` itself: the ledger). By
    default ``ledger`` in registered mode and ``settings`` in signed mode.
    """
    configure_logging(service, settings.log_level)
    data_dir = settings.resolved_data_dir()
    data_dir.mkdir(parents=True, exist_ok=True)
    metrics = ServiceMetrics(service)
    reserve = DiskReserve(data_dir, settings.disk_reserve_bytes)
    metrics.watch_disk(reserve)
    background = BackgroundTasks()
    nonces = NonceStore(data_dir / "nonces.log", settings.max_clock_skew_s)
    authorizer = build_authorizer(settings)
    source = deployment_source or ("ledger" if settings.auth == "registered" else "settings")
    audience = _service_audience(settings, source)

    async def audience_known() -> None:
        audience.require()

    @asynccontextmanager
    async def run(app: FastAPI) -> AsyncIterator[None]:
        log.info("starting", extra={"port": settings.resolved_port(), "auth": settings.auth})
        try:
            async with anyio.create_task_group() as tasks:
                if source == "ledger":
                    background.start(
                        tasks, "learn-deployment", partial(_learn_deployment, audience, settings)
                    )
                if lifespan is None:
                    yield
                else:
                    async with lifespan(app):
                        yield
                tasks.cancel_scope.cancel()
        finally:
            nonces.close()
            authorizer.close()
            log.info("stopped")

    app = FastAPIOffline(
        title=f"robocloud {service}",
        version=robocloud.__version__,
        description=description,
        lifespan=run,
        static_url=DOCS_ASSETS,
    )
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.disk_reserve = reserve
    app.state.nonces = nonces
    app.state.authorizer = authorizer
    app.state.audience = audience
    app.state.background = background
    app.state.on_stop = []
    """What to call once the process is told to stop, before uvicorn waits for the requests
    in flight (see ``runner.serve``): a long poll answers then, not after the drain timeout."""
    app.state.readiness_checks = [audience_known, background.all_running, *readiness_checks]
    _install_error_handlers(app, COMMON_ERRORS | (errors or ErrorMap({})))
    app.include_router(_framework_router(service, settings, audience))
    for router in routers:
        app.include_router(router)
    # Starlette runs the middleware added last first: the request id wraps everything.
    app.add_middleware(
        DiskReserveLayer,
        reserve=reserve,
        storing_paths=storing_paths,
    )
    app.add_middleware(
        SignatureLayer,
        audience=audience,
        nonces=nonces,
        authorizer=authorizer,
        max_clock_skew_s=settings.max_clock_skew_s,
        unsigned_paths=unsigned_paths,
        routed=partial(_routed, app.router.routes),
    )
    app.add_middleware(
        BodyLimitLayer,
        default_limit=settings.max_body_bytes,
        limits={"/v1/whoami": min(SMALL_JSON_BODY, settings.max_body_bytes), **(body_limits or {})},
    )
    app.add_middleware(AccessLogLayer, metrics=metrics)
    app.add_middleware(RequestIdLayer)
    return app


def _routed(routes: Sequence[BaseRoute], scope: Scope) -> bool:
    """Whether one of ``routes`` takes the request's method at its path."""
    return any(route.matches(scope)[0] is Match.FULL for route in routes)


def _service_audience(settings: ServiceSettings, source: DeploymentSource) -> ServiceAudience:
    name = settings.resolved_audience_name()
    if source == "settings":
        deployment = settings.deployment_id or LOCAL_DEPLOYMENT
        return ServiceAudience(name, deployment, source="ROBOCLOUD_DEPLOYMENT_ID")
    if source == "ledger":
        return ServiceAudience(name, source=f"the ledger at {settings.ledger_url}")
    return ServiceAudience(name, source="the chain")


async def _learn_deployment(audience: ServiceAudience, settings: ServiceSettings) -> None:
    await learn_from_ledger(audience, settings.ledger_url, expected=settings.deployment_id)
