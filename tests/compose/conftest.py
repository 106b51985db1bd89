"""Fixtures for tests against the Compose deployment (run by ``make test-compose`` only).

A new area's compose test is one file here using ``deployment``: ``deployment.urls[name]``,
``deployment.client(name)`` (signed as the allowed identity), ``deployment.restart([...])``;
mark the module with ``pytestmark = pytest.mark.compose``.
"""

from __future__ import annotations

import pytest

from tests.compose.deployment import Deployment


@pytest.fixture(scope="session")
def deployment() -> Deployment:
    return Deployment.from_env()
