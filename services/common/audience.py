"""The audience a service accepts signatures for, ``<service>@<deployment>``, and how it is known.

The service part is the service's name (or the replica name an operator sets). The deployment
id comes from one of three places: the settings, for a service that runs without a ledger
(``ROBOCLOUD_AUTH=signed``, ``ROBOCLOUD_DEPLOYMENT_ID``, default ``local``); the ledger's
``GET /v1/audience``, for a service in ``registered`` mode, which is not ready and refuses
signed requests (503) until it has learned it; or the service itself, for the ledger, which
owns the chain and the Registry the id names.
"""

from __future__ import annotations

import logging

import anyio

from robocloud.errors import RobocloudError
from robocloud.ledger import LedgerService
from robocloud.signing import CHAIN_DEPLOYMENT_ID, Audience, AudienceError, parse_audience
from services.common.errors import Unavailable

log = logging.getLogger("robocloud.audience")


class ServiceAudience:
    """This service's audience once its deployment id is known."""

    def __init__(self, name: str, deployment: str | None = None, *, source: str) -> None:
        self.name = name
        self.source = source
        self.problem: str | None = None
        self._audience = None if deployment is None else Audience(name, deployment)

    @property
    def known(self) -> Audience | None:
        return self._audience

    def learn(self, deployment: str) -> None:
        """Take the deployment id from the chain (the ledger) or from the ledger's answer."""
        if not CHAIN_DEPLOYMENT_ID.fullmatch(deployment):
            raise AudienceError(f"{deployment[:200]!r} is not <chain id>:<registry address>")
        self._audience = Audience(self.name, deployment)
        self.problem = None
        log.info("audience known", extra={"audience": str(self._audience)})

    def require(self) -> Audience:
        """The audience; 503 while it is not known, since nothing signed can be checked yet."""
        if self._audience is None:
            why = self.problem or f"it has not yet learned its deployment id from {self.source}"
            raise Unavailable(
                f"this service cannot check signatures: {why}",
                code="audience_unknown",
                details={"source": self.source},
            )
        return self._audience


async def learn_from_ledger(
    audience: ServiceAudience,
    ledger_url: str,
    *,
    expected: str | None = None,
    timeout_s: float = 5.0,
    retry_s: float = 0.2,
    max_retry_s: float = 5.0,
) -> None:
    """Ask the ledger for the deployment id until it answers, then stop.

    ``expected`` (``ROBOCLOUD_DEPLOYMENT_ID`` in registered mode) pins the deployment: a ledger
    of any other deployment leaves the service unready, with the reason in ``/readyz``.

    Each problem is logged once, when it appears, not at every retry: under ``make up`` the
    services start before the ledger listens, and each wrote a warning every few hundred
    milliseconds until it did.
    """
    delay = retry_s
    with LedgerService(ledger_url, timeout=timeout_s, retries=0) as ledger:
        while True:
            said = audience.problem
            try:
                deployment = await anyio.to_thread.run_sync(_deployment_of, ledger)
            except RobocloudError as exc:
                audience.problem = f"the ledger at {ledger_url} did not tell it ({exc})"
                if audience.problem != said:
                    log.warning("deployment id not learned yet", extra={"reason": str(exc)})
            else:
                if expected is None or deployment == expected:
                    audience.learn(deployment)
                    return
                audience.problem = (
                    f"the ledger at {ledger_url} serves deployment {deployment}, "
                    f"but ROBOCLOUD_DEPLOYMENT_ID is {expected}"
                )
                if audience.problem != said:
                    log.error(
                        "wrong ledger", extra={"deployment": deployment, "expected": expected}
                    )
            await anyio.sleep(delay)
            delay = min(delay * 2, max_retry_s)


def _deployment_of(ledger: LedgerService) -> str:
    """The deployment id the ledger's audience names (the SDK bounds and parses the answer)."""
    deployment = parse_audience(ledger.audience()).deployment
    if not CHAIN_DEPLOYMENT_ID.fullmatch(deployment):
        raise AudienceError(f"the ledger's deployment {deployment!r} is not <chain id>:<registry>")
    return deployment
