"""Blocks on disk, one file per multihash, never trusted on read.

A block lives at ``blocks/<2 hex>/<multihash hex>``: keyed by multihash like kubo, so a raw
and a dag-pb CID of the same bytes share one file. Writes are staged (temporary file,
fsync) and renamed into place, so a crash leaves either no file or the whole block under a
name. Every read re-hashes the file: a block whose bytes no longer match (disk rot, an
operator's mistake) is moved to ``quarantine/`` and reported, and the read fails as a miss
so that the caller can fetch a good copy from a peer.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from robocloud.cid import CID, RAW, CIDError
from services.common.durable import fsync_dir

log = logging.getLogger("robocloud.cas.blockstore")

CorruptionHook = Callable[[CID, Path], None]


class BlockNotFound(KeyError):
    """No good copy of the block here (never stored, removed, or quarantined)."""

    def __init__(self, cid: CID, reason: str = "not in this store") -> None:
        super().__init__(str(cid))
        self.cid = cid
        self.reason = reason


@dataclass(frozen=True)
class StoredBlock:
    """A block file as garbage collection sees it."""

    multihash: bytes
    size: int
    modified: float


def _write_synced(path: Path, data: bytes | memoryview) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    finally:
        os.close(fd)


class Blockstore:
    """Verified block storage under one directory."""

    def __init__(self, root: Path, on_corrupt: CorruptionHook | None = None) -> None:
        self.root = root
        self.blocks = root / "blocks"
        self.quarantine = root / "quarantine"
        self.staging = root / "staging"
        self.on_corrupt = on_corrupt
        for directory in (self.blocks, self.quarantine, self.staging):
            directory.mkdir(parents=True, exist_ok=True)
        self._clear_staging()

    def _clear_staging(self) -> None:
        """Uploads interrupted by a crash were never acknowledged: drop what they staged."""
        for leftover in self.staging.iterdir():
            shutil.rmtree(leftover, ignore_errors=True)

    def path(self, cid: CID) -> Path:
        name = cid.multihash.hex()
        return self.blocks / name[-2:] / name

    def has(self, cid: CID) -> bool:
        return self.path(cid).is_file()

    def size(self, cid: CID) -> int:
        try:
            return self.path(cid).stat().st_size
        except FileNotFoundError:
            raise BlockNotFound(cid) from None

    def get(self, cid: CID) -> bytes:
        """The block's bytes, re-hashed; a mismatch quarantines the file and raises a miss."""
        path = self.path(cid)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise BlockNotFound(cid) from None
        try:
            cid.verify(data)
        except CIDError:
            self._quarantine(cid, path)
            raise BlockNotFound(cid, "corrupted on disk and quarantined") from None
        return data

    def put(self, cid: CID, data: bytes | memoryview) -> bool:
        """Store a block after checking it; False when it was already here."""
        cid.verify(data)
        with self.stage() as staged:
            staged.add(cid, data)
            return staged.commit() > 0

    def stage(self) -> Staging:
        return Staging(self)

    def delete(self, multihash: bytes) -> None:
        name = multihash.hex()
        (self.blocks / name[-2:] / name).unlink(missing_ok=True)

    def stored(self) -> Iterator[StoredBlock]:
        for shard in self.blocks.iterdir():
            for path in shard.iterdir():
                try:
                    stat = path.stat()
                except FileNotFoundError:
                    continue
                yield StoredBlock(bytes.fromhex(path.name), stat.st_size, stat.st_mtime)

    def _quarantine(self, cid: CID, path: Path) -> None:
        target = self.quarantine / f"{path.name}.{int(time.time())}"
        try:
            os.replace(path, target)
        except FileNotFoundError:
            return
        log.error("corrupted block quarantined", extra={"cid": str(cid), "file": str(target)})
        if self.on_corrupt is not None:
            self.on_corrupt(cid, target)


class Staging:
    """Blocks of one upload, durable on disk but invisible until ``commit``.

    An upload that fails half-way (a truncated body, a bad block in a CAR) is discarded by
    leaving the context without committing: nothing of it ever appears in the store.
    """

    def __init__(self, store: Blockstore) -> None:
        self.store = store
        self.directory = store.staging / uuid.uuid4().hex
        self.directory.mkdir()
        self._staged: dict[bytes, Path] = {}

    def __enter__(self) -> Staging:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.discard()

    def __contains__(self, cid: CID) -> bool:
        return cid.multihash in self._staged

    def add(self, cid: CID, data: bytes | memoryview) -> None:
        """Stage a block the caller has already checked against ``cid``."""
        if cid.multihash in self._staged or self.store.has(cid):
            return
        path = self.directory / cid.multihash.hex()
        _write_synced(path, data)
        self._staged[cid.multihash] = path

    def get(self, cid: CID) -> bytes:
        path = self._staged.get(cid.multihash)
        if path is None:
            return self.store.get(cid)
        return path.read_bytes()

    def commit(self) -> int:
        """Move every staged block into the store; returns how many were new."""
        shards: set[Path] = set()
        for multihash, path in self._staged.items():
            name = multihash.hex()
            shard = self.store.blocks / name[-2:]
            shard.mkdir(exist_ok=True)
            os.replace(path, shard / name)
            shards.add(shard)
        for shard in shards:
            fsync_dir(shard)
        committed = len(self._staged)
        self._staged.clear()
        return committed

    def discard(self) -> None:
        shutil.rmtree(self.directory, ignore_errors=True)
        self._staged.clear()


def cid_for_multihash(multihash: bytes) -> CID:
    """The name kubo gives a stored block in listings: the store keeps no codec, so raw."""
    return CID(1, RAW, multihash)
