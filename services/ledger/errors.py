"""How the ledger's domain exceptions are answered over HTTP (JSON-RPC has its own codes)."""

from __future__ import annotations

from services.common.errors import ErrorMap, ErrorRule
from services.ledger.faucet import RateLimited
from services.ledger.node import FaucetFailed, FaucetUnavailable
from services.ledger.views import InvalidAddress, InvalidLimit, RobotNotFound


def _retry_after(exc: RateLimited) -> int:
    return max(1, round(exc.retry_after_s))


ERRORS = ErrorMap(
    {
        InvalidAddress: ErrorRule(400, "invalid_address", lambda exc: {exc.name: exc.value}),
        InvalidLimit: ErrorRule(400, "invalid_limit", lambda exc: {"limit": exc.value}),
        RobotNotFound: ErrorRule(404, "robot_not_found", lambda exc: {"address": exc.address}),
        FaucetUnavailable: ErrorRule(404, "faucet_unavailable"),
        FaucetFailed: ErrorRule(
            503, "faucet_failed", lambda _: {"retry_after": 1}, lambda _: {"Retry-After": "1"}
        ),
        RateLimited: ErrorRule(
            429,
            "faucet_rate_limited",
            lambda exc: {"retry_after": _retry_after(exc), "address": exc.address},
            lambda exc: {"Retry-After": str(_retry_after(exc))},
        ),
    }
)
