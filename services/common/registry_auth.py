"""``ROBOCLOUD_AUTH=registered``: writers must be registered, active robots on the ledger.

The ledger service answers ``GET /v1/robots/{address}`` from its event index; this authorizer
asks it and caches each answer briefly (10 s by default, 2 s for "not registered" so that a
robot that has just registered is let in soon), because a signed request would otherwise
cost a round trip to the ledger. A revocation therefore takes effect within the cache
lifetime. When the ledger cannot be reached the request is refused with 503: failing open
would let anybody write whenever the ledger is down.

Addresses in ``ROBOCLOUD_ALLOWED_ADDRESSES`` are the operator's own keys (its tools, the
Compose test): allowed without asking, and in every role, since the operator could grant
itself any role on its ledger anyway. A robot's key does not belong there.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Iterable

import anyio
from eth_utils.address import is_address, to_checksum_address

from robocloud.errors import ApiError, InvalidAnswerError, TransportError
from robocloud.ledger import LedgerService
from robocloud.ledger.models import RegisteredRobot
from services.common.errors import UNKNOWN_SIGNER, Forbidden, Unavailable

MAX_CACHED = 10_000
"""Registry answers kept at once. Past it the least recently used goes, one at a time:
strangers' one-off addresses then push out each other, not the robots that keep writing."""


class RegistryAuthorizer:
    """Allows active registered robots (holding ``role`` when one is asked for)."""

    def __init__(
        self,
        ledger_url: str,
        allowed: Iterable[str] = (),
        *,
        cache_s: float = 10.0,
        negative_cache_s: float = 2.0,
        timeout_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        max_cached: int = MAX_CACHED,
    ) -> None:
        self.ledger_url = ledger_url.rstrip("/")
        self.ledger = LedgerService(self.ledger_url, timeout=timeout_s, retries=1)
        self.allowed = frozenset(to_checksum_address(a) for a in allowed if is_address(a))
        self.cache_s = cache_s
        self.negative_cache_s = negative_cache_s
        self.clock = clock
        self.max_cached = max_cached
        self._cache: OrderedDict[str, tuple[float, float, RegisteredRobot | None]] = OrderedDict()
        """Per address: when its record expires, when it was fetched, and the record."""

    async def authorize(self, address: str, role: str | None = None) -> None:
        """Raise 403 unless ``address`` may write (holding ``role`` when one is asked for).
        A role the robot lacks is checked against a record at most ``negative_cache_s`` old,
        as any refusal is: a role is granted right after a refusal (``admin grant`` once
        ``role_required`` came back), and the record the refusal cached for ``cache_s``
        refused the robot's retry too."""
        if address in self.allowed:
            return
        robot = await self.robot(address)
        if role is not None and robot is not None and role not in robot.roles:
            robot = await self.robot(address, max_age_s=self.negative_cache_s)
        _require_standing(address, robot, role)

    async def holds_role(self, address: str, role: str) -> bool:
        if address in self.allowed:
            return True
        robot = await self.robot(address)
        return robot is not None and robot.active and role in robot.roles

    async def robot(
        self, address: str, *, max_age_s: float | None = None
    ) -> RegisteredRobot | None:
        """The ledger's record of ``address`` (None when unregistered), cached briefly;
        asked again when the cached one is older than ``max_age_s``."""
        now = self.clock()
        cached = self._cache.get(address)
        if (
            cached is not None
            and cached[0] > now
            and (max_age_s is None or now - cached[1] <= max_age_s)
        ):
            self._cache.move_to_end(address)
            return cached[2]
        robot = await self._fetch(address)
        lifetime = (
            self.cache_s if robot is not None and not robot.pending else self.negative_cache_s
        )
        self._cache[address] = (now + lifetime, now, robot)
        self._cache.move_to_end(address)
        while len(self._cache) > self.max_cached:
            self._cache.popitem(last=False)
        return robot

    async def _fetch(self, address: str) -> RegisteredRobot | None:
        try:
            return await anyio.to_thread.run_sync(self.ledger.robot, address)
        except TransportError as exc:
            raise Unavailable(
                "cannot reach the ledger to check the signer's registration",
                code="ledger_unreachable",
                details={"ledger_url": self.ledger_url},
            ) from exc
        except (ApiError, InvalidAnswerError) as exc:
            raise Unavailable(
                f"the ledger could not answer a registration check: {exc}",
                code="ledger_unavailable",
                details={"ledger_url": self.ledger_url},
            ) from exc

    def close(self) -> None:
        self.ledger.close()


def _require_standing(address: str, robot: RegisteredRobot | None, role: str | None) -> None:
    """Raise 403 unless ``robot``, the ledger's record of ``address``, is registered, active,
    and holds ``role`` when one is asked for."""
    if robot is None:
        raise Forbidden(
            f"address {address} is not a registered robot on the ledger "
            "(`robocloud register` registers it)",
            code=UNKNOWN_SIGNER,
            details={"address": address},
        )
    if robot.pending:
        raise Forbidden(
            f"robot {address} asked to register and awaits approval by the ledger's admin or "
            f"a registrar (`robocloud admin approve {address}`)",
            code="registration_pending",
            details={"address": address},
        )
    if not robot.active:
        raise Forbidden(
            f"robot {address} is deactivated or suspended",
            code="robot_inactive",
            details={"address": address},
        )
    if role is not None and role not in robot.roles:
        raise Forbidden(
            f"robot {address} does not hold the role {role}",
            code="role_required",
            details={"address": address, "role": role},
        )
