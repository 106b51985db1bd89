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
import httpx

from robocloud.errors import FormatError
from robocloud.signing import CHAIN_DEPLOYMENT_ID, Audience, AudienceError, audience_from_answer
from services.common.errors import Unavailable

log = logging.getLogger("robocloud.audience")

MAX_ANSWER_BYTES = 4096
"""An audience answer is under 200 bytes; anything longer is not one."""


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
    """
    url = f"{ledger_url.rstrip('/')}/v1/audience"
    delay = retry_s
    async with httpx.AsyncClient(timeout=timeout_s) as client:
        while True:
            try:
                deployment = await _ask(client, url)
            except (httpx.HTTPError, FormatError, _NotAnswered) as exc:
                audience.problem = f"the ledger at {ledger_url} did not tell it ({exc})"
                log.warning("deployment id not learned yet", extra={"reason": str(exc)})
            else:
                if expected is None or deployment == expected:
                    audience.learn(deployment)
                    return
                audience.problem = (
                    f"the ledger at {ledger_url} serves deployment {deployment}, "
                    f"but ROBOCLOUD_DEPLOYMENT_ID is {expected}"
                )
                log.error("wrong ledger", extra={"deployment": deployment, "expected": expected})
            await anyio.sleep(delay)
            delay = min(delay * 2, max_retry_s)


class _NotAnswered(Exception):
    """The ledger answered, but not with its audience (starting, or not a ledger)."""


async def _ask(client: httpx.AsyncClient, url: str) -> str:
    async with client.stream("GET", url) as response:
        if response.status_code != 200:
            raise _NotAnswered(f"{url} answered {response.status_code}")
        body = b""
        async for chunk in response.aiter_bytes():
            body += chunk
            if len(body) > MAX_ANSWER_BYTES:
                raise _NotAnswered(f"{url} answered more than {MAX_ANSWER_BYTES} bytes")
    deployment = audience_from_answer(body).deployment
    if not CHAIN_DEPLOYMENT_ID.fullmatch(deployment):
        raise _NotAnswered(f"the ledger's deployment {deployment!r} is not <chain id>:<registry>")
    return deployment
