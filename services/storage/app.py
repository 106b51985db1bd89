"""Routes of the storage service."""

from __future__ import annotations

from fastapi import FastAPI

import services.storage
from services.common.app import create_app
from services.common.settings import ServiceSettings


def build_app(settings: ServiceSettings) -> FastAPI:
    return create_app("storage", settings, description=services.storage.__doc__ or "")
