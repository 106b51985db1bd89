"""Settings from ``ROBOCLOUD_*`` environment variables, one model for every service.

A service that needs more subclasses :class:`ServiceSettings`; defaults are the loopback
addresses and ports fixed in ARCHITECTURE.md so ``make up`` needs no configuration.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, Self, TypeVar

from pydantic import BeforeValidator, Field, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from robocloud.config import SERVICES as DEFAULT_PORTS
from robocloud.signing import DEPLOYMENT_ID, SERVICE_NAME


def _split_commas(value: object) -> object:
    if isinstance(value, str):
        return [part.strip() for part in value.split(",") if part.strip()]
    return value


CommaList = Annotated[list[str], NoDecode, BeforeValidator(_split_commas)]
"""A list setting written in the environment as ``a,b,c``."""


class ServiceSettings(BaseSettings):
    """Settings every service understands."""

    model_config = SettingsConfigDict(env_prefix="ROBOCLOUD_", extra="ignore")

    service: str = "robocloud"
    host: str = "127.0.0.1"
    port: int = Field(default=0, ge=0, le=65535)
    data_dir: Path | None = None
    auth: Literal["registered", "signed"] = "registered"
    allowed_addresses: CommaList = Field(default_factory=list)
    audience_name: str | None = Field(
        default=None,
        pattern=SERVICE_NAME.pattern,
        description="the service part of this service's audience; default the service's name",
    )
    deployment_id: str | None = Field(
        default=None,
        pattern=DEPLOYMENT_ID.pattern,
        description="signed mode: the deployment id (default local); registered mode: must "
        "equal the ledger's when set",
    )
    max_body_bytes: int = Field(default=16 * 1024 * 1024, gt=0)
    max_request_line_bytes: int = Field(default=8 * 1024, ge=64)
    max_header_bytes: int = Field(default=64 * 1024, ge=256)
    header_timeout_s: float = Field(default=30.0, gt=0)
    body_timeout_s: float = Field(
        default=30.0, gt=0, description="a request body may pause at most this long"
    )
    send_timeout_s: float = Field(
        default=30.0, gt=0, description="a client must take each piece of an answer within this"
    )
    max_clock_skew_s: int = Field(default=300, gt=0)
    disk_reserve_bytes: int = Field(
        default=256 * 1024 * 1024,
        ge=0,
        description="free disk space that uploads may not take: what the service's own small "
        "writes (nonces, journals, indexes) and deletions need once robots have filled the rest",
    )
    trusted_proxies: CommaList = Field(
        default_factory=list,
        description="addresses whose X-Forwarded-For names the client (a reverse proxy's); "
        "none by default, so no client can claim another's address",
    )
    log_level: str = "INFO"
    cas_url: str = f"http://127.0.0.1:{DEFAULT_PORTS['cas']}"
    ledger_url: str = f"http://127.0.0.1:{DEFAULT_PORTS['ledger']}"
    storage_url: str = f"http://127.0.0.1:{DEFAULT_PORTS['storage']}"
    broker_url: str = f"http://127.0.0.1:{DEFAULT_PORTS['broker']}"
    fl_url: str = f"http://127.0.0.1:{DEFAULT_PORTS['fl']}"

    @model_validator(mode="after")
    def _request_line_within_head(self) -> Self:
        if self.max_request_line_bytes > self.max_header_bytes:
            raise ValueError("max_request_line_bytes must not exceed max_header_bytes")
        return self

    def resolved_port(self) -> int:
        return self.port or DEFAULT_PORTS.get(self.service, 8000)

    def resolved_audience_name(self) -> str:
        return self.audience_name or self.service

    def resolved_data_dir(self) -> Path:
        return self.data_dir or Path("data") / self.service


S = TypeVar("S", bound=ServiceSettings)


def load_settings(service: str, cls: type[S]) -> S:
    """Read the environment for ``service``; ``cls`` lets a service add its own fields."""
    settings = cls(service=service)
    settings.data_dir = settings.resolved_data_dir()
    settings.port = settings.resolved_port()
    return settings
