"""A content store in a fresh directory, no peers, closed after the test."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from services.cas.store import ContentStore


@pytest.fixture
def store(tmp_path: Path) -> Iterator[ContentStore]:
    opened = ContentStore.open(tmp_path, [])
    yield opened
    opened.close()
