"""The content store: blocks, pins and peers behind the operations robots ask for.

Everything here is synchronous file work with no knowledge of HTTP; the routes run it in
worker threads. Errors are :mod:`services.common.errors` exceptions naming the CID at fault.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from robocloud.car import ByteSource, CarError, CarReader, write_car
from robocloud.cid import CID, DAG_PB, CIDError
from robocloud.unixfs import (
    Block,
    Importer,
    ImportParams,
    PBNode,
    UnixfsError,
    file_size,
    read_file,
    walk_dag,
)
from services.cas.blockstore import BlockNotFound, Blockstore, Staging, cid_for_multihash
from services.cas.peers import PeerFetcher
from services.cas.pins import PinSet
from services.common.errors import BadRequest, NotFound, ServiceError

log = logging.getLogger("robocloud.cas.store")

DAG_SCOPES = ("block", "entity", "all")


def parse_cid(text: str, field: str = "arg") -> CID:
    """A CID from a request, or 400 naming the field and quoting the value."""
    try:
        return CID.decode(text)
    except CIDError as exc:
        raise BadRequest(
            str(exc), code="invalid_cid", details={"field": field, "cid": text}
        ) from exc


class NotAFile(BadRequest):
    code = "not_a_file"


@dataclass(frozen=True)
class AddedFile:
    """One file of an ``add``: kubo reports its name, root CID and cumulative DAG size."""

    name: str
    cid: CID
    dag_size: int
    file_size: int


@dataclass(frozen=True)
class ImportedRoot:
    cid: CID
    pin_error: str


class FileAdder:
    """Imports the files of one upload into a staging area; ``commit`` makes them visible.

    Fed from a worker thread while the body streams in; nothing is visible in the store until
    the whole body has arrived and matched its signed digest.
    """

    def __init__(self, store: ContentStore, params: ImportParams, *, only_hash: bool) -> None:
        self.store = store
        self.params = params
        self.only_hash = only_hash
        self.staging = store.blocks.stage()
        self.added: list[AddedFile] = []
        self._importer: Importer | None = None
        self._name = ""
        self._dag_size = 0

    def begin(self, name: str) -> None:
        self._importer = Importer(self.params)
        self._name = name
        self._dag_size = 0

    def write(self, data: bytes) -> None:
        assert self._importer is not None, "write before begin"
        self._stage(self._importer.feed(data))

    def end(self) -> None:
        assert self._importer is not None, "end before begin"
        blocks, root, size = self._importer.finish()
        self._stage(blocks)
        self.added.append(AddedFile(self._name or str(root), root, self._dag_size, size))
        self._importer = None

    def _stage(self, blocks: list[Block]) -> None:
        for block in blocks:
            self._dag_size += len(block.data)
            if not self.only_hash:
                self.staging.add(block.cid, block.data)

    def commit(self, owner: str, pin: bool) -> list[AddedFile]:
        if not self.only_hash:
            self.staging.commit()
            if pin:
                for added in self.added:
                    self.store.pins.add(added.cid, owner)
        self.staging.discard()
        return self.added

    def discard(self) -> None:
        self.staging.discard()


class ContentStore:
    def __init__(self, root: Path, blocks: Blockstore, peers: PeerFetcher | None = None) -> None:
        self.blocks = blocks
        self.pins = PinSet(root / "pins.log")
        self.peers = peers

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
        raise NotFound(
            f"block {cid} is {reason}", code="block_not_found", details={"cid": str(cid)}
        )

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
            raise NotAFile(str(exc), details={"cid": str(root)}) from exc

    def read(
        self, root: CID, offset: int = 0, length: int | None = None, *, use_peers: bool = True
    ) -> Iterator[bytes]:
        """The file's bytes in ``[offset, offset + length)``, each block verified as read."""
        try:
            yield from read_file(
                root, lambda cid: self.get_block(cid, use_peers=use_peers), offset, length
            )
        except UnixfsError as exc:
            raise NotAFile(str(exc), details={"cid": str(root)}) from exc

    def adder(self, params: ImportParams, *, only_hash: bool = False) -> FileAdder:
        return FileAdder(self, params, only_hash=only_hash)

    # ---- DAGs and CARs ----

    def blocks_of(
        self, root: CID, scope: str = "all", *, use_peers: bool = True
    ) -> Iterator[Block]:
        if scope not in DAG_SCOPES:
            raise BadRequest(
                f"unknown dag-scope {scope!r}: expected one of {', '.join(DAG_SCOPES)}",
                code="invalid_dag_scope",
                details={"field": "dag-scope"},
            )
        try:
            yield from walk_dag(root, lambda cid: self.get_block(cid, use_peers=use_peers), scope)
        except UnixfsError as exc:
            raise BadRequest(str(exc), code="invalid_dag", details={"cid": str(root)}) from exc

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
            raise BadRequest(
                f"rejected the CAR, nothing was stored: {exc}", code="invalid_car"
            ) from exc
        return reader.roots

    def missing_block(self, root: CID, staging: Staging | None = None) -> CID | None:
        """The first block of ``root``'s DAG that neither the store nor its peers have."""
        try:
            for _ in walk_dag(root, lambda cid: self._staged_or_stored(cid, staging), "all"):
                pass
        except _Missing as missing:
            return missing.cid
        except UnixfsError as exc:
            raise BadRequest(str(exc), code="invalid_dag", details={"cid": str(root)}) from exc
        return None

    def _staged_or_stored(self, cid: CID, staging: Staging | None) -> bytes:
        if staging is not None and cid in staging:
            return staging.get(cid)
        try:
            return self.get_block(cid)
        except ServiceError:
            raise _Missing(cid) from None

    # ---- pins and garbage collection ----

    def pin(self, root: CID, owner: str) -> None:
        """Pin a DAG for ``owner`` once all its blocks are here (fetched from peers if need be)."""
        missing = self.missing_block(root)
        if missing is not None:
            raise NotFound(
                f"cannot pin {root}: block {missing} of its DAG is not available",
                code="block_not_found",
                details={"cid": str(root), "missing": str(missing)},
            )
        self.pins.add(root, owner)

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
            except (BlockNotFound, UnixfsError):
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
