"""Routes of the fl service."""

from __future__ import annotations

from fastapi import FastAPI

import services.fl
from services.common.app import create_app
from services.common.settings import ServiceSettings


def build_app(settings: ServiceSettings) -> FastAPI:
    return create_app("fl", settings, description=services.fl.__doc__ or "")
