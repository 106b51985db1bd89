"""Where the services are, from the same ``ROBOCLOUD_*_URL`` variables the services read."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation

from robocloud.errors import ConfigurationError

SERVICES: dict[str, int] = {
    "cas": 8080,
    "ledger": 8545,
    "storage": 8082,
    "broker": 8083,
    "fl": 8084,
}
"""Each service's default port (ARCHITECTURE.md); the services read the same table."""

DEFAULT_MAX_GAS = 5_000_000
"""The most gas a robot signs a transaction for unless told otherwise: robocloud's calls take
well under 500,000 and deploying the Registry about 2,500,000, so a node that estimates
more is lying or the call is not what the robot meant."""
DEFAULT_MAX_FEE_PER_GAS_GWEI = 100
"""The most a robot pays per gas unless told otherwise (at most 0.5 ether a transaction with
``DEFAULT_MAX_GAS``); a development chain asks about 2 gwei."""
GWEI = 10**9
_LEDGER_DEPLOYMENT = re.compile(r"(\d{1,20}):(0x[0-9a-fA-F]{40})")


def service_url(service: str) -> str:
    """``$ROBOCLOUD_<SERVICE>_URL``, else the service's loopback default."""
    if service not in SERVICES:
        raise ValueError(f"unknown service {service!r}; expected one of {', '.join(SERVICES)}")
    default = f"http://127.0.0.1:{SERVICES[service]}"
    return os.environ.get(f"ROBOCLOUD_{service.upper()}_URL", default).rstrip("/")


def expected_deployment() -> str | None:
    """``$ROBOCLOUD_EXPECTED_DEPLOYMENT``: the deployment this robot means to talk to, if it
    says.

    The SDK then signs only for services that claim it; unset, it signs for the deployment a
    service claims (docs/signing.md). Not the services' ``ROBOCLOUD_DEPLOYMENT_ID``, their own
    id, which in ``signed`` mode differs from the ledger's their SDK clients sign for.
    """
    return os.environ.get("ROBOCLOUD_EXPECTED_DEPLOYMENT") or None


def deployment_chain(deployment: str | None) -> tuple[int, str] | None:
    """The chain id and Registry address (lower case) a deployment id names, if it names them.

    A deployment with a ledger is ``<chain id>:<Registry address>``; any other id (``local``,
    a service run without a ledger) says nothing about a chain, so nothing is checked against it.
    """
    match = _LEDGER_DEPLOYMENT.fullmatch(deployment or "")
    if match is None:
        return None
    return int(match.group(1)), match.group(2).lower()


def max_gas() -> int:
    """``$ROBOCLOUD_MAX_GAS``: the most gas this robot signs one transaction for."""
    text = os.environ.get("ROBOCLOUD_MAX_GAS")
    if not text:
        return DEFAULT_MAX_GAS
    if not re.fullmatch(r"[0-9]{1,12}", text.strip()) or int(text) == 0:
        raise ConfigurationError(f"ROBOCLOUD_MAX_GAS={text[:40]!r} is not a positive integer")
    return int(text)


def max_fee_per_gas() -> int:
    """``$ROBOCLOUD_MAX_FEE_PER_GAS_GWEI`` in wei: the most this robot pays per gas."""
    text = os.environ.get("ROBOCLOUD_MAX_FEE_PER_GAS_GWEI")
    if not text:
        return DEFAULT_MAX_FEE_PER_GAS_GWEI * GWEI
    try:
        gwei = Decimal(text.strip())
    except InvalidOperation:
        gwei = Decimal(-1)
    if not gwei.is_finite() or gwei <= 0 or gwei > 10**12:
        raise ConfigurationError(
            f"ROBOCLOUD_MAX_FEE_PER_GAS_GWEI={text[:40]!r} is not a positive number of gwei"
        )
    return int(gwei * GWEI)


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
