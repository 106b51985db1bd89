"""Settings of the cas service (``ROBOCLOUD_CAS_*``), beside those every service has."""

from __future__ import annotations

from pydantic import Field

from services.common.settings import CommaList, ServiceSettings


class CasSettings(ServiceSettings):
    cas_peers: CommaList = Field(
        default_factory=list, description="other gateways to fetch missing blocks from"
    )
    cas_peer_timeout_s: float = Field(default=10.0, gt=0)
    cas_max_upload_bytes: int = Field(default=4 * 1024**3, gt=0)
    cas_max_upload_entries: int = Field(
        default=250_000, gt=0, description="files and directories one add may hold"
    )
    cas_max_pinned_bytes_per_robot: int = Field(
        default=16 * 1024**3,
        gt=0,
        description="bytes of pinned DAGs one robot may keep (storage nodes and "
        "ROBOCLOUD_ALLOWED_ADDRESSES are not bounded): past it a pin is 507 quota_exceeded",
    )
    cas_max_written_bytes_per_robot_per_hour: int = Field(
        default=16 * 1024**3,
        gt=0,
        description="new bytes one robot may store in a rolling hour, pinned or not (storage "
        "nodes and ROBOCLOUD_ALLOWED_ADDRESSES are not bounded): past it an upload is 429 "
        "write_rate_exceeded",
    )
    cas_max_cached_bytes_per_hour: int = Field(
        default=8 * 1024**3,
        gt=0,
        description="bytes reads may fetch from peers and keep in a rolling hour; past it a "
        "block fetched for a read is served without being kept",
    )
    cas_gc_grace_s: float = Field(default=3600.0, ge=0)
    cas_max_streams: int = Field(
        default=64,
        gt=0,
        description="file, cat and CAR answers streaming at once; more wait up to 5 s, "
        "then are refused (503 busy)",
    )
    cas_gc_interval_s: float = Field(default=3600.0, ge=0, description="0 disables periodic GC")
