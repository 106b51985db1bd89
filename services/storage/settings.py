"""Settings of the storage service (``ROBOCLOUD_STORAGE_*``), beside those every service has.

Each engineer's settings sit in their own block, so that additions merge without conflicts.
"""

from __future__ import annotations

from pydantic import Field

from services.common.settings import ServiceSettings


class StorageSettings(ServiceSettings):
    # ----- templates, records, segments and queries (engineer records) -----
    storage_segment_records: int = Field(
        default=4096, ge=16, le=1_000_000, description="records per sealed TinyDB segment"
    )
    storage_segment_cache: int = Field(
        default=64, ge=1, description="sealed segments kept decoded in memory for queries"
    )
    storage_array_inline_bytes: int = Field(
        default=4096, ge=64, description="arrays larger than this (canonical JSON) go to cas"
    )
    storage_max_batch_records: int = Field(
        default=10_000, gt=0, description="records one POST /v1/records may hold"
    )
    storage_max_batch_bytes: int = Field(
        default=64 * 1024 * 1024, gt=0, description="bytes one POST /v1/records may hold"
    )
    storage_max_line_bytes: int = Field(
        default=1024 * 1024, gt=0, description="bytes of one record (NDJSON line or array item)"
    )
    storage_max_templates: int = Field(
        default=100_000, gt=0, description="template versions the catalog holds at most"
    )

    # ----- bag ingestion and export (engineer bags) -----
    storage_max_bag_bytes: int = Field(
        default=16 * 1024**3, gt=0, description="bytes of one bag, uploaded or fetched from cas"
    )
    storage_ingest_batch_records: int = Field(
        default=5000, ge=1, le=100_000, description="records per append while committing a bag"
    )
    storage_max_ingest_jobs: int = Field(
        default=16, ge=1, description="ingest jobs queued or running at once"
    )
