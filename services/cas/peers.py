"""Fetching missing blocks from other gateways over the trustless gateway protocol.

A peer is trusted for nothing: every block it returns is hashed against the CID asked for,
and a peer that answers wrong bytes (or errors, or times out) is skipped for the next one.
Requests carry ``Cache-Control: only-if-cached`` so a peer answers from its own store only
and two gateways that list each other cannot bounce a miss back and forth.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

from robocloud.cas import Cas, CasError
from robocloud.cid import CID
from robocloud.errors import ApiError, RobocloudError

log = logging.getLogger("robocloud.cas.peers")

OutcomeHook = Callable[[str, str], None]
NOT_THERE = (404, 412)
"""A peer that does not hold the block answers 404, or 412 to ``only-if-cached``."""


class PeerFetcher:
    """Asks each configured gateway in turn for a block and returns the first good copy."""

    def __init__(
        self,
        peers: Sequence[str],
        *,
        timeout_s: float = 10.0,
        on_outcome: OutcomeHook | None = None,
    ) -> None:
        self.peers = [peer.rstrip("/") for peer in peers]
        self.on_outcome = on_outcome
        self._clients = {peer: Cas(peer, timeout=timeout_s, retries=0) for peer in self.peers}

    def fetch(self, cid: CID) -> bytes | None:
        for peer in self.peers:
            data = self._fetch_from(peer, cid)
            if data is not None:
                return data
        return None

    def _fetch_from(self, peer: str, cid: CID) -> bytes | None:
        try:
            data = self._clients[peer].block(cid, cached_only=True)
        except CasError as exc:
            self._report(peer, cid, "bad_block", reason=str(exc))
            return None
        except ApiError as exc:
            if exc.status in NOT_THERE:
                self._report(peer, cid, "miss")
            else:
                self._report(peer, cid, "error", reason=str(exc))
            return None
        except RobocloudError as exc:
            self._report(peer, cid, "error", reason=str(exc))
            return None
        self._report(peer, cid, "ok")
        return data

    def _report(self, peer: str, cid: CID, outcome: str, reason: str = "") -> None:
        level = logging.WARNING if outcome in ("bad_block", "error") else logging.DEBUG
        log.log(
            level,
            "peer fetch",
            extra={"peer": peer, "cid": str(cid), "outcome": outcome, "reason": reason},
        )
        if self.on_outcome is not None:
            self.on_outcome(peer, outcome)

    def close(self) -> None:
        for client in self._clients.values():
            client.close()
