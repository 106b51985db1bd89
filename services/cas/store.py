"""The content store: blocks, pins and peers behind the operations robots ask for.

Everything here is synchronous file work with no knowledge of HTTP; the routes run it in
worker threads. Failures are the exceptions below, each naming the CID at fault;
``services.cas.errors`` says how each is answered.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from robocloud.car import ByteSource, CarError, CarReader, write_car
from robocloud.cid import CID, DAG_PB, Block
from robocloud.dagpb import DagPbError, PBNode
from robocloud.unixfs import UnixfsError, file_size, read_file, walk_dag
from services.cas.blockstore import (
    BlockNotFound,
    Blockstore,
    CorruptionHook,
    Staging,
    cid_for_multihash,
)
from services.cas.peers import OutcomeHook, PeerFetcher
from services.cas.pins import PinSet

log = logging.getLogger("robocloud.cas.store")

DAG_SCOPES = ("block", "entity", "all")


class BlockUnavailable(LookupError):
    """No verified copy of a block here or at any peer asked."""

    def __init__(self, cid: CID, reason: str) -> None:
        super().__init__(f"block {cid} is {reason}")
        self.cid = cid


class DagIncomplete(LookupError):
    """A DAG to pin lacks a block that neither this store nor its peers have."""

    def __init__(self, root: CID, missing: CID) -> None:
        super().__init__(f"cannot pin {root}: block {missing} of its DAG is not available")
        self.root = root
        self.missing = missing


class NotAFile(ValueError):
    """The CID names something that is not a readable UnixFS file (or lies about its size)."""

    def __init__(self, cid: CID, reason: str) -> None:
        super().__init__(reason)
        self.cid = cid


class InvalidDag(ValueError):
    """A DAG that cannot be walked: a block that does not decode, or a path too deep."""

    def __init__(self, cid: CID, reason: str) -> None:
        super().__init__(reason)
        self.cid = cid


class CarRejected(ValueError):
    """An imported CAR with a bad block or framing; nothing of it was stored."""

    def __init__(self, reason: str) -> None:
        super().__init__(f"rejected the CAR, nothing was stored: {reason}")


class UnknownScope(ValueError):
    def __init__(self, scope: str) -> None:
        super().__init__(f"unknown dag-scope {scope!r}: expected one of {', '.join(DAG_SCOPES)}")
        self.scope = scope


class UnpinnedArgument(ValueError):
    """A CID asked about in a pin listing that nobody pinned."""

    def __init__(self, cid: CID) -> None:
        super().__init__(f"{cid} is not pinned")
        self.cid = cid


@dataclass(frozen=True)
class ImportedRoot:
    """A root of an imported CAR; ``pin_error`` says why it was not pinned, if it was not."""

    cid: CID
    pin_error: str


class ContentStore:
    def __init__(self, root: Path, blocks: Blockstore, peers: PeerFetcher | None = None) -> None:
        self.blocks = blocks
        self.pins = PinSet(root / "pins.log")
        self.peers = peers

    @classmethod
    def open(
        cls,
        root: Path,
        peers: list[str],
        *,
        peer_timeout_s: float = 10.0,
        on_corrupt: CorruptionHook | None = None,
        on_peer_outcome: OutcomeHook | None = None,
    ) -> ContentStore:
        """The store under ``root``, fetching missing blocks from ``peers`` (gateway URLs)."""
        fetcher = None
        if peers:
            fetcher = PeerFetcher(peers, timeout_s=peer_timeout_s, on_outcome=on_peer_outcome)
        return cls(root, Blockstore(root, on_corrupt=on_corrupt), fetcher)

    def check_writable(self) -> None:
        """Raise ``OSError`` unless the pack directory is there (a readiness check)."""
        self.blocks.packs.stat()

    def usage(self) -> tuple[int, int]:
        """Blocks stored, and the bytes their packs take on disk."""
        return self.blocks.usage()

    # ---- blocks ----

    def get_block(self, cid: CID, *, use_peers: bool = True) -> bytes:
        """A verified block: local, else from a peer (then cached); 404 naming the CID."""
        try:
            return self.blocks.get(cid)
        except BlockNotFound as miss:
            reason = miss.reason
        if use_peers and self.peers is not None:
            data = self.peers.fetch(cid)
            if data is not None:
                self.blocks.put(cid, data)
                return data
            reason += "; no peer has it"
        raise BlockUnavailable(cid, reason)

    def block_size(self, cid: CID, *, use_peers: bool = True) -> int:
        if self.blocks.has(cid):
            return self.blocks.size(cid)
        return len(self.get_block(cid, use_peers=use_peers))

    def put_blocks(self, blocks: list[bytes], codec: int, owner: str, *, pin: bool) -> list[CID]:
        """Store raw blocks as one pack (one fsync, all or none), then pin them if asked."""
        cids = [CID.from_block(data, codec, 1) for data in blocks]
        with self.blocks.stage() as staging:
            for cid, data in zip(cids, blocks, strict=True):
                staging.add(cid, data)
            staging.commit()
        if pin:
            for cid in dict.fromkeys(cids):
                self.pins.add(cid, owner)
        return cids

    # ---- files ----

    def file_size(self, root: CID, *, use_peers: bool = True) -> int:
        try:
            return file_size(root, lambda cid: self.get_block(cid, use_peers=use_peers))
        except UnixfsError as exc:
            raise NotAFile(root, str(exc)) from exc

    def read(
        self, root: CID, offset: int = 0, length: int | None = None, *, use_peers: bool = True
    ) -> Iterator[bytes]:
        """The file's bytes in ``[offset, offset + length)``, each block verified as read."""
        try:
            yield from read_file(
                root, lambda cid: self.get_block(cid, use_peers=use_peers), offset, length
            )
        except UnixfsError as exc:
            raise NotAFile(root, str(exc)) from exc

    # ---- DAGs and CARs ----

    def blocks_of(
        self, root: CID, scope: str = "all", *, use_peers: bool = True
    ) -> Iterator[Block]:
        if scope not in DAG_SCOPES:
            raise UnknownScope(scope)
        try:
            yield from walk_dag(root, lambda cid: self.get_block(cid, use_peers=use_peers), scope)
        except UnixfsError as exc:
            raise InvalidDag(root, str(exc)) from exc

    def export_car(
        self, root: CID, scope: str = "all", *, use_peers: bool = True
    ) -> Iterator[bytes]:
        return write_car([root], self.blocks_of(root, scope, use_peers=use_peers))

    def import_car(self, staging: Staging, source: ByteSource) -> list[CID]:
        """Stage every block of a CAR; any bad block raises and the caller discards it all."""
        try:
            reader = CarReader(source)
            for block in reader:
                staging.add(block.cid, block.data)
        except CarError as exc:
            raise CarRejected(str(exc)) from exc
        return reader.roots

    def missing_block(self, root: CID, staging: Staging | None = None) -> CID | None:
        """The first block of ``root``'s DAG that neither the store nor its peers have."""
        try:
            for _ in walk_dag(root, lambda cid: self._staged_or_stored(cid, staging), "all"):
                pass
        except _Missing as missing:
            return missing.cid
        except UnixfsError as exc:
            raise InvalidDag(root, str(exc)) from exc
        return None

    def _staged_or_stored(self, cid: CID, staging: Staging | None) -> bytes:
        if staging is not None and cid in staging:
            return staging.get(cid)
        try:
            return self.get_block(cid)
        except BlockUnavailable:
            raise _Missing(cid) from None

    # ---- pins and garbage collection ----

    def pin(self, root: CID, owner: str) -> None:
        """Pin a DAG for ``owner`` once all its blocks are here (fetched from peers if need be)."""
        missing = self.missing_block(root)
        if missing is not None:
            raise DagIncomplete(root, missing)
        self.pins.add(root, owner)

    def unpin(self, roots: list[CID], owner: str) -> None:
        """Remove ``owner``'s pins on every root, or none (see ``PinSet.remove``)."""
        self.pins.remove(roots, owner)

    def pinned(self, wanted: list[CID] | None = None) -> dict[CID, frozenset[str]]:
        """Pinned roots and their owners; only ``wanted`` ones, each of which must be pinned."""
        pins = self.pins.snapshot()
        if not wanted:
            return pins
        for cid in wanted:
            if cid not in pins:
                raise UnpinnedArgument(cid)
        return {cid: pins[cid] for cid in wanted}

    def collect_garbage(self, grace_s: float, now: float | None = None) -> list[CID]:
        """Remove every unpinned block older than ``grace_s``; never a block of a pinned DAG.

        The grace period protects blocks an upload just wrote and is about to pin, and blocks
        a robot pushed with ``block/put`` before pinning the root that links them.
        """
        cutoff = (now if now is not None else time.time()) - grace_s
        live: set[bytes] = set()
        for root in self.pins.snapshot():
            self._mark_reachable(root, live)
        dead = [
            stored.multihash
            for stored in self.blocks.stored()
            if stored.multihash not in live and stored.committed < cutoff
        ]
        self.blocks.delete(dead)
        self.blocks.compact()
        return [cid_for_multihash(multihash) for multihash in dead]

    def _mark_reachable(self, root: CID, live: set[bytes]) -> None:
        """Mark every stored block under ``root``, going on past missing or corrupt ones."""
        stack = [root]
        while stack:
            cid = stack.pop()
            if cid.multihash in live:
                continue
            live.add(cid.multihash)
            if cid.codec != DAG_PB:
                continue
            try:
                node = PBNode.decode(self.blocks.get(cid))
            except (BlockNotFound, DagPbError):
                log.warning("pinned DAG incomplete during gc", extra={"cid": str(cid)})
                continue
            stack.extend(link.cid for link in node.links)

    def close(self) -> None:
        self.pins.close()
        if self.peers is not None:
            self.peers.close()


class _Missing(Exception):
    def __init__(self, cid: CID) -> None:
        super().__init__(str(cid))
        self.cid = cid
