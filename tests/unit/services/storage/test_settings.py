"""Storage settings an operator can get wrong, refused at start with the variable named."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from services.storage.settings import SMALLEST_STAGING_MEMORY_BYTES, StorageSettings


def test_a_staging_memory_bound_no_process_starts_in_is_refused_at_start(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Before, the service started and every ingest job failed with a bare ``MemoryError``."""
    monkeypatch.setenv("ROBOCLOUD_STORAGE_INGEST_WORKER_MEMORY_BYTES", str(256 * 1024**2))
    with pytest.raises(ValidationError) as refused:
        StorageSettings(service="storage")
    [error] = refused.value.errors()
    assert error["loc"] == ("storage_ingest_worker_memory_bytes",)
    assert f"at least {SMALLEST_STAGING_MEMORY_BYTES} bytes, or 0 for no bound" in error["msg"]


@pytest.mark.parametrize("bound", [0, SMALLEST_STAGING_MEMORY_BYTES, 2 * 1024**3])
def test_no_bound_and_bounds_a_process_starts_in_are_taken(bound: int) -> None:
    settings = StorageSettings(service="storage", storage_ingest_worker_memory_bytes=bound)
    assert settings.storage_ingest_worker_memory_bytes == bound


def test_a_knowledge_base_larger_than_a_worker_can_load_is_refused_at_start(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Before, every worker died loading the graph, again and again, and no query was
    answered."""
    monkeypatch.setenv("ROBOCLOUD_KNOWLEDGE_MAX_TOTAL_BYTES", str(2 * 1024**3))
    with pytest.raises(ValidationError) as refused:
        StorageSettings(service="storage")
    [error] = refused.value.errors()
    assert "(ROBOCLOUD_KNOWLEDGE_MAX_TOTAL_BYTES)" in error["msg"]
    assert "more than ROBOCLOUD_KNOWLEDGE_WORKER_MEMORY_BYTES (4294967296)" in error["msg"]


def test_rdflibs_memory_store_holds_less_in_the_same_memory() -> None:
    with pytest.raises(ValidationError, match="in the memory store needs about"):
        StorageSettings(service="storage", knowledge_store="memory")
    StorageSettings(
        service="storage", knowledge_store="memory", knowledge_max_total_bytes=256 * 1024**2
    )


@pytest.mark.parametrize(("total", "memory"), [(512 * 1024**2, 4 * 1024**3), (2 * 1024**3, 0)])
def test_a_knowledge_base_a_worker_can_load_is_taken(total: int, memory: int) -> None:
    settings = StorageSettings(
        service="storage", knowledge_max_total_bytes=total, knowledge_worker_memory_bytes=memory
    )
    assert settings.knowledge_max_total_bytes == total
