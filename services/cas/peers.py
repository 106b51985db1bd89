"""Fetching missing blocks from other gateways over the trustless gateway protocol.

A peer is trusted for nothing: every block it returns is hashed against the CID asked for,
and a peer that answers wrong bytes (or errors, or times out) is skipped for the next one.
Requests carry ``Cache-Control: only-if-cached`` so a peer answers from its own store only
and two gateways that list each other cannot bounce a miss back and forth.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import httpx

from robocloud.cid import CID, CIDError

log = logging.getLogger("robocloud.cas.peers")

RAW_MEDIA_TYPE = "application/vnd.ipld.raw"
MAX_BLOCK_BYTES = 4 * 1024 * 1024
OutcomeHook = Callable[[str, str], None]


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
        self._http = httpx.Client(timeout=timeout_s, follow_redirects=False)

    def fetch(self, cid: CID) -> bytes | None:
        for peer in self.peers:
            data = self._fetch_from(peer, cid)
            if data is not None:
                return data
        return None

    def _fetch_from(self, peer: str, cid: CID) -> bytes | None:
        try:
            data = self._download(peer, cid)
        except httpx.HTTPError as exc:
            self._report(peer, cid, "error", reason=str(exc) or type(exc).__name__)
            return None
        if data is None:
            self._report(peer, cid, "miss")
            return None
        try:
            cid.verify(data)
        except CIDError:
            self._report(peer, cid, "bad_block", reason="returned bytes that do not match the CID")
            return None
        self._report(peer, cid, "ok")
        return data

    def _download(self, peer: str, cid: CID) -> bytes | None:
        headers = {"Accept": RAW_MEDIA_TYPE, "Cache-Control": "only-if-cached"}
        url = f"{peer}/ipfs/{cid}"
        with self._http.stream("GET", url, params={"format": "raw"}, headers=headers) as response:
            if response.status_code != 200:
                return None
            body = bytearray()
            for chunk in response.iter_bytes():
                body += chunk
                if len(body) > MAX_BLOCK_BYTES:
                    raise httpx.DecodingError(f"block larger than {MAX_BLOCK_BYTES} bytes")
            return bytes(body)

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
        self._http.close()
