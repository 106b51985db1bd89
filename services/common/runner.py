"""Running a service process: ``python -m services.<name>`` ends here."""

from __future__ import annotations

from collections.abc import Callable

import uvicorn
from fastapi import FastAPI

from services.common.settings import S, ServiceSettings, load_settings


def serve(app: FastAPI, settings: ServiceSettings) -> None:
    """Serve until SIGINT or SIGTERM, then drain in-flight requests for a few seconds."""
    uvicorn.run(
        app,
        host=settings.host,
        port=settings.resolved_port(),
        log_config=None,
        access_log=False,
        server_header=False,
        timeout_graceful_shutdown=5,
    )


def run_service(
    service: str,
    build_app: Callable[[S], FastAPI],
    settings_cls: type[S] = ServiceSettings,  # type: ignore[assignment]
) -> None:
    """Load the service's settings from the environment, build its app and serve it."""
    settings = load_settings(service, settings_cls)
    serve(build_app(settings), settings)
