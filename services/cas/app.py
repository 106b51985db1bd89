"""Routes of the cas service."""

from __future__ import annotations

from fastapi import FastAPI

import services.cas
from services.common.app import create_app
from services.common.settings import ServiceSettings


def build_app(settings: ServiceSettings) -> FastAPI:
    return create_app("cas", settings, description=services.cas.__doc__ or "")
