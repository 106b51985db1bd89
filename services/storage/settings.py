"""Settings of the storage service (``ROBOCLOUD_STORAGE_*``), beside those every service has.

Each engineer's settings sit in their own block, so that additions merge without conflicts.
"""

from __future__ import annotations

import os
from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator

from robocloud.client import MAX_WAIT_S
from services.common.settings import ServiceSettings
from services.storage.ingest import (
    KEEP_RESUMABLE_S,
    PUBLISH_ATTEMPTS,
    PUBLISH_RETRY_MAX_S,
    PUBLISH_RETRY_S,
)

SMALLEST_STAGING_MEMORY_BYTES = 320 * 1024**2
"""Below it every job failed as ``ingest_failed`` with a bare ``MemoryError``: 256 MiB could
not start a staging process, 300 MiB staged a small bag (measured 2026-11-28)."""
WORKER_BYTES_PER_DESCRIPTION_BYTE = {"oxigraph": 3, "memory": 10}
"""A SPARQL worker's memory per byte of canonical N-Triples it loads, by store: measured 2.2
with Oxigraph (100,000 file descriptions, 151 MB, peaked at 408 MB of address space over an
empty worker's 80 MB) and 8.8 with rdflib's memory store (20,000, 30 MB, 332 MB), rounded up
for descriptions of more, shorter terms."""
WORKER_BASE_BYTES = 256 * 1024**2
"""An empty worker's address space (80 MB measured), with room to answer queries."""


class StorageSettings(ServiceSettings):
    # ----- record log, epochs and anchoring (engineer anchor) -----
    storage_epoch_s: float = Field(
        default=2.0, gt=0, le=2.0, description="the longest an epoch lasts (at most 2 s)"
    )
    storage_epoch_records: int = Field(
        default=10_000, gt=0, description="an epoch ends early once this many records arrived"
    )
    storage_anchor: bool = Field(
        default=True, description="anchor each epoch's TMT root through AnchorLog"
    )
    storage_anchor_retry_s: float = Field(
        default=1.0,
        gt=0,
        description="wait before retrying a failed anchor (doubles to 30 s; not while the "
        "node only waits for its role)",
    )
    storage_receipt_timeout_s: float = Field(
        default=60.0,
        ge=1,
        le=3600,
        description="wait for an anchor's or advertisement's receipt; one still pending after "
        "it is replaced at a higher gas price on the next attempt",
    )
    storage_node_passphrase: SecretStr | None = Field(
        default=None, description="encrypts the node's keystore; generated when unset"
    )
    storage_register: bool = Field(
        default=True,
        description="register the node's key on the Registry at start (faucet on a dev chain)",
    )

    # ----- knowledge base (engineer semantic) -----
    knowledge_workers: int = Field(
        default=2, ge=1, le=16, description="SPARQL worker processes, each with a copy of the graph"
    )
    knowledge_query_timeout_s: float = Field(
        default=10.0,
        gt=0,
        le=300,
        description="a query (waiting for a worker included) is stopped after this long",
    )
    knowledge_max_query_bytes: int = Field(
        default=64 * 1024, gt=0, description="the longest SPARQL query accepted"
    )
    knowledge_max_result_bytes: int = Field(
        default=16 * 1024 * 1024, gt=0, description="the largest SPARQL answer sent"
    )
    knowledge_worker_memory_bytes: int = Field(
        default=4 * 1024**3, ge=0, description="address space of a SPARQL worker (0: unbounded)"
    )
    knowledge_max_total_bytes: int = Field(
        default=512 * 1024**2,
        gt=0,
        description="the canonical N-Triples of every description together; past it a new "
        "description is 507 knowledge_base_full (each worker holds the whole graph)",
    )
    knowledge_max_bytes_per_robot: int = Field(
        default=64 * 1024**2,
        gt=0,
        description="what the descriptions one robot adds (signed or advertised) may take; "
        "past it its next one is 507 quota_exceeded",
    )
    knowledge_store: Literal["memory", "oxigraph"] = Field(
        default="oxigraph", description="the rdflib store behind SPARQL (docs/semantics.md)"
    )
    knowledge_follow_ledger: bool = Field(
        default=True, description="index descriptions advertised on the ledger"
    )
    knowledge_poll_s: float = Field(
        default=2.0,
        gt=0,
        description="the least time between two reads of the ledger's advertisements",
    )
    knowledge_wait_s: float = Field(
        default=20.0,
        ge=0,
        le=MAX_WAIT_S,
        description="how long one read waits on the ledger for a new advertisement",
    )

    def node_passphrase(self) -> str | None:
        secret = self.storage_node_passphrase
        return secret.get_secret_value() if secret is not None else None

    # ----- templates, records, segments and queries (engineer records) -----
    storage_segment_records: int = Field(
        default=4096, ge=16, le=1_000_000, description="records per sealed TinyDB segment"
    )
    storage_segment_cache: int = Field(
        default=16, ge=1, description="sealed segments kept decoded in memory for queries"
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
    storage_max_queries: int = Field(
        default=2,
        gt=0,
        description="record queries, state intervals and export pages running at once; more "
        "wait up to storage_query_wait_s, then are refused (503 busy)",
    )
    storage_max_exports: int = Field(
        default=16,
        gt=0,
        description="GET /v1/export answers streaming at once (each holds a page of records); "
        "more wait up to storage_query_wait_s, then are refused (503 busy)",
    )
    storage_query_wait_s: float = Field(
        default=5.0, gt=0, description="how long a query waits for its turn before the 503"
    )
    storage_max_templates: int = Field(
        default=100_000, gt=0, description="template versions the catalog holds at most"
    )
    storage_max_template_bytes: int = Field(
        default=64 * 1024**2,
        gt=0,
        description="bytes of template versions (as journalled) the catalog holds at most; "
        "its memory is about five times that",
    )

    # ----- bag ingestion and export (engineer bags) -----
    storage_max_bag_bytes: int = Field(
        default=16 * 1024**3, gt=0, description="bytes of one bag, uploaded or fetched from cas"
    )
    storage_max_bag_entries: int = Field(
        default=1024,
        ge=1,
        le=100_000,
        description="entries of a ROS 2 bag directory ingested by CID (metadata.yaml, parts)",
    )
    storage_ingest_batch_records: int = Field(
        default=5000, ge=1, le=100_000, description="records per append while committing a bag"
    )
    storage_ingest_workers: int = Field(
        default_factory=lambda: min(4, os.cpu_count() or 1),
        ge=1,
        le=64,
        description="processes staging a large bag, each a time window of it (default: the "
        "machine's cores, at most 4); the service never decodes a bag's message itself",
    )
    storage_ingest_parallel_messages: int = Field(
        default=20_000,
        ge=1,
        description="bound messages from which a bag is staged by all those processes, each "
        "a time window of it; one of them stages a smaller bag",
    )
    storage_ingest_worker_memory_bytes: int = Field(
        default=2 * 1024**3,
        ge=0,
        description="address space of a process staging a bag (0: unbounded, else at least "
        "320 MiB); a message decoding to more fails its job (message_too_large)",
    )
    storage_ingest_stall_s: float = Field(
        default=120.0,
        gt=0,
        description="a staging process that sends nothing for this long is stuck: its job "
        "fails (ingest_stalled)",
    )
    storage_max_ingest_jobs: int = Field(
        default=16, ge=1, description="ingest jobs queued or running at once"
    )
    storage_max_ingest_jobs_per_robot: int = Field(
        default=4,
        ge=1,
        description="ingest jobs one robot may have queued or running at once, so that one "
        "robot's bags never hold every place in the queue",
    )
    storage_keep_resumable_s: float = Field(
        default=KEEP_RESUMABLE_S,
        gt=0,
        description="how long a job that failed while committing keeps its bag and spool for "
        "a resume; then they are removed and the job is failed for good",
    )
    storage_publish_datasets: bool = Field(
        default=True,
        description="describe each ingested bag, index it and advertise it on the ledger",
    )
    storage_publish_attempts: int = Field(
        default=PUBLISH_ATTEMPTS,
        ge=1,
        le=100,
        description="attempts to publish a dataset (cas or the ledger out) before its bag is "
        "removed unpublished",
    )
    storage_publish_retry_s: float = Field(
        default=PUBLISH_RETRY_S,
        gt=0,
        description="wait after a dataset's first failed publish; it doubles after each "
        f"failure, up to {PUBLISH_RETRY_MAX_S:g} s",
    )

    @model_validator(mode="after")
    def _knowledge_fits_a_worker(self) -> StorageSettings:
        memory = self.knowledge_worker_memory_bytes
        ratio = WORKER_BYTES_PER_DESCRIPTION_BYTE[self.knowledge_store]
        needed = self.knowledge_max_total_bytes * ratio
        if 0 < memory < needed + WORKER_BASE_BYTES:
            raise ValueError(
                f"a SPARQL worker holding {self.knowledge_max_total_bytes} bytes of descriptions "
                f"(ROBOCLOUD_KNOWLEDGE_MAX_TOTAL_BYTES) in the {self.knowledge_store} store "
                f"needs about {needed + WORKER_BASE_BYTES} bytes of memory, more than "
                f"ROBOCLOUD_KNOWLEDGE_WORKER_MEMORY_BYTES ({memory}): it would die loading them; "
                "lower the first or raise the second"
            )
        return self

    @field_validator("storage_ingest_worker_memory_bytes")
    @classmethod
    def _staging_process_can_start(cls, value: int) -> int:
        if 0 < value < SMALLEST_STAGING_MEMORY_BYTES:
            raise ValueError(
                f"a staging process maps about 300 MiB (the interpreter, rosbags, numpy) before "
                f"it reads a message: give it at least {SMALLEST_STAGING_MEMORY_BYTES} bytes, "
                "or 0 for no bound"
            )
        return value
