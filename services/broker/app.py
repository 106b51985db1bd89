"""Routes of the broker service."""

from __future__ import annotations

from fastapi import FastAPI

import services.broker
from services.common.app import create_app
from services.common.settings import ServiceSettings


def build_app(settings: ServiceSettings) -> FastAPI:
    return create_app("broker", settings, description=services.broker.__doc__ or "")
