"""Running a service process: ``python -m services.<name>`` ends here."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from types import FrameType

import uvicorn
from fastapi import FastAPI

from services.common.server import bounded_protocol
from services.common.settings import S, ServiceSettings, load_settings

log = logging.getLogger("robocloud.runner")

DEFAULT_RECURSION_LIMIT = 1000
"""CPython's own default, which the C stack of the main thread and of worker threads (8 MiB)
holds with room to spare. py_ecc (imported by eth-account) raises the limit to 100,000 at
import, and py-evm to 12,288: deep recursion in C code (the JSON decoder, ``repr`` and
comparison of nested containers) then overflows the C stack and kills the process with a
segfault instead of raising RecursionError."""

DEFAULT_SWITCH_INTERVAL_S = 0.005
"""CPython's own default: how long a thread may hold the GIL while another waits for it."""
BUSY_THREADS_SWITCH_INTERVAL_S = 0.0005
"""For a service whose worker threads run long pure-Python work beside the event loop (the
ledger's calls, storage's queries). Under a flood of looping calls a ledger transfer took
0.6-0.9 s at the default, 0.03-0.09 s at this; with nothing running beside it, unchanged."""


class _Server(uvicorn.Server):
    """uvicorn's server, calling the app's ``on_stop`` callbacks when a signal stops it:
    uvicorn drains the requests in flight before the app's lifespan hears of the stop."""

    def __init__(self, config: uvicorn.Config, on_stop: list[Callable[[], None]]) -> None:
        super().__init__(config)
        self.on_stop = on_stop

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        super().handle_exit(sig, frame)
        for callback in list(self.on_stop):
            callback()


def serve(app: FastAPI, settings: ServiceSettings) -> None:
    """Serve until SIGINT or SIGTERM, then drain in-flight requests for a few seconds.

    The client is the peer address unless ``trusted_proxies`` names the peer: uvicorn trusts
    ``X-Forwarded-For`` from loopback by default, which would let any local client claim a new
    address a request, out of the share of turns its own address holds (``slots``).
    """
    config = uvicorn.Config(
        app,
        host=settings.host,
        port=settings.resolved_port(),
        http=bounded_protocol(
            settings.max_request_line_bytes,
            settings.max_header_bytes,
            settings.header_timeout_s,
            settings.body_timeout_s,
            settings.send_timeout_s,
        ),
        h11_max_incomplete_event_size=settings.max_header_bytes,
        proxy_headers=bool(settings.trusted_proxies),
        forwarded_allow_ips=settings.trusted_proxies or None,
        log_config=None,
        access_log=False,
        server_header=False,
        timeout_graceful_shutdown=5,
    )
    _Server(config, app.state.on_stop).run()


def run_service(
    service: str,
    build_app: Callable[[S], FastAPI],
    settings_cls: type[S] = ServiceSettings,  # type: ignore[assignment]
    *,
    recursion_limit: int = DEFAULT_RECURSION_LIMIT,
    switch_interval_s: float = DEFAULT_SWITCH_INTERVAL_S,
) -> None:
    """Load the service's settings from the environment, build its app and serve it.

    The recursion limit is set once everything is imported (importing is what raises it); a
    service whose own code needs more (the ledger's EVM) declares it here. So does a service
    whose worker threads run long pure-Python work beside its event loop (the ledger's
    calls): every time the loop gives up the GIL for I/O it waits up to the switch interval
    per busy thread to take it back, many times a request.
    """
    settings = load_settings(service, settings_cls)
    app = build_app(settings)
    sys.setrecursionlimit(recursion_limit)
    sys.setswitchinterval(switch_interval_s)
    log.info(
        "serving",
        extra={
            "recursion_limit": sys.getrecursionlimit(),
            "switch_interval_s": sys.getswitchinterval(),
            "max_request_line_bytes": settings.max_request_line_bytes,
            "max_header_bytes": settings.max_header_bytes,
            "header_timeout_s": settings.header_timeout_s,
            "body_timeout_s": settings.body_timeout_s,
            "send_timeout_s": settings.send_timeout_s,
        },
    )
    serve(app, settings)
