"""Routes of the ledger service."""

from __future__ import annotations

from fastapi import FastAPI

import services.ledger
from services.common.app import create_app
from services.common.settings import ServiceSettings


def build_app(settings: ServiceSettings) -> FastAPI:
    return create_app("ledger", settings, description=services.ledger.__doc__ or "")
