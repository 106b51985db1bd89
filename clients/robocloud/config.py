"""Where the services are, from the same ``ROBOCLOUD_*_URL`` variables the services read."""

from __future__ import annotations

import os
from dataclasses import dataclass

SERVICES: dict[str, int] = {
    "cas": 8080,
    "ledger": 8545,
    "storage": 8082,
    "broker": 8083,
    "fl": 8084,
}
"""Each service's default port (ARCHITECTURE.md); the services read the same table."""


def service_url(service: str) -> str:
    """``$ROBOCLOUD_<SERVICE>_URL``, else the service's loopback default."""
    if service not in SERVICES:
        raise ValueError(f"unknown service {service!r}; expected one of {', '.join(SERVICES)}")
    default = f"http://127.0.0.1:{SERVICES[service]}"
    return os.environ.get(f"ROBOCLOUD_{service.upper()}_URL", default).rstrip("/")


def expected_deployment() -> str | None:
    """``$ROBOCLOUD_DEPLOYMENT_ID``: the deployment this robot means to talk to, if it says.

    The SDK then signs only for services that claim it; unset, it signs for the deployment a
    service claims (docs/signing.md).
    """
    return os.environ.get("ROBOCLOUD_DEPLOYMENT_ID") or None


@dataclass(frozen=True)
class Endpoints:
    """The base URL of every service."""

    cas: str
    ledger: str
    storage: str
    broker: str
    fl: str

    @classmethod
    def from_env(cls) -> Endpoints:
        return cls(**{name: service_url(name) for name in SERVICES})

    def items(self) -> list[tuple[str, str]]:
        return [(name, getattr(self, name)) for name in SERVICES]
