"""Blocks on disk in pack files, keyed by multihash, never trusted on read.

One file per block (kubo's flatfs) pays a file creation, an fsync and a rename per 256 KiB:
on the ext4 volumes measured here that alone capped uploads at about 200 MiB/s. Instead an
upload appends its blocks to one new pack file (``packs/<id>.pack``) and, once the whole
body has arrived, commits it: the pack is fsynced, then its index (``<id>.idx``: multihash,
offset, length per block) is written atomically (temporary file, fsync, rename). A pack
without an index is an upload that never committed and is deleted at start, so a crash
never leaves a partial block under a CID. Keyed by multihash like kubo, a raw and a dag-pb
CID of the same bytes share one stored block.

Every read re-hashes the bytes: a block that no longer matches (disk rot, an operator's
mistake) is copied to ``quarantine/``, dropped from its pack's index and reported, and the
read fails as a miss so that the caller can fetch a good copy from a peer. Deleted blocks
leave dead bytes in their pack until ``compact`` rewrites it.

Garbage collection runs beside uploads and pins, so what an operation relies on is held
(:class:`Hold`): a block an upload found already stored and did not write again, a block
it committed and is about to pin, a block a pin check has read. ``collect`` deletes no
held block, and a hold is given back only under ``sweeping``, the lock collection's last
phase takes: a hold ends either before that phase, when its pin is already there to be
marked, or after it.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from robocloud.cid import CID, IDENTITY, RAW, CIDError
from services.common.durable import atomic_write, fsync_dir

log = logging.getLogger("robocloud.cas.blockstore")

CorruptionHook = Callable[[CID, Path], None]


class BlockNotFound(KeyError):
    """No good copy of the block here (never stored, removed, or quarantined)."""

    def __init__(self, cid: CID, reason: str = "not in this store") -> None:
        super().__init__(str(cid))
        self.cid = cid
        self.reason = reason


@dataclass(frozen=True, slots=True)
class Location:
    pack: str
    offset: int
    length: int


@dataclass(frozen=True)
class StoredBlock:
    """A block as garbage collection sees it: when it was last put.

    That is its pack's commit, or a later upload that found it already stored: a robot
    pushing a block before the root linking it has the grace period to pin the root, even
    when another robot stored the block long ago.
    """

    multihash: bytes
    size: int
    put_at: float


class Blockstore:
    """Verified block storage under one directory."""

    def __init__(self, root: Path, on_corrupt: CorruptionHook | None = None) -> None:
        self.packs = root / "packs"
        self.quarantine = root / "quarantine"
        self.spool = root / "spool"
        self.on_corrupt = on_corrupt
        for directory in (self.packs, self.quarantine, self.spool):
            directory.mkdir(parents=True, exist_ok=True)
        for leftover in self.spool.iterdir():
            leftover.unlink()
        for directory in (self.packs, self.quarantine):
            remove_temporaries(directory)
        self._lock = threading.Lock()
        self.sweeping = threading.Lock()
        """Held by garbage collection's last phase (marking new pins, then ``collect``)."""
        self._held: Counter[bytes] = Counter()
        self._index: dict[bytes, Location] = {}
        self._members: dict[str, dict[bytes, Location]] = {}
        self._committed: dict[str, float] = {}
        self._put_again: dict[bytes, float] = {}
        """When an upload last found a block already stored: in memory only, so after a
        restart a block counts from its pack's commit again (docs/cas.md, Storage)."""
        self._load()

    def _load(self) -> None:
        """Read every committed pack's index; delete packs whose upload never committed."""
        for idx in sorted(self.packs.glob("*.idx")):
            entries = json.loads(idx.read_bytes())
            members = {
                bytes.fromhex(key): Location(idx.stem, offset, length)
                for key, offset, length in entries
            }
            self._members[idx.stem] = members
            self._committed[idx.stem] = idx.stat().st_mtime
            self._index.update(members)
        for pack in self.packs.glob("*.pack"):
            if pack.stem not in self._members:
                log.info("dropping uncommitted pack", extra={"pack": pack.name})
                pack.unlink()

    def pack_path(self, pack: str) -> Path:
        return self.packs / f"{pack}.pack"

    def locate(self, cid: CID) -> Location:
        with self._lock:
            location = self._index.get(cid.multihash)
        if location is None:
            raise BlockNotFound(cid)
        return location

    def has(self, cid: CID) -> bool:
        with self._lock:
            return cid.multihash in self._index

    def size(self, cid: CID) -> int:
        return self.locate(cid).length

    def get(self, cid: CID) -> bytes:
        """The block's bytes, re-hashed; a mismatch quarantines it and raises a miss."""
        for _ in range(3):
            location = self.locate(cid)
            try:
                with self.pack_path(location.pack).open("rb") as pack:
                    pack.seek(location.offset)
                    data = pack.read(location.length)
                break
            except FileNotFoundError:
                continue  # compacted away meanwhile: the index now points at its new pack
        else:
            raise BlockNotFound(cid, "moving between packs; try again")
        try:
            if len(data) != location.length:
                raise CIDError("truncated")
            cid.verify(data)
        except CIDError:
            self._quarantine(cid, location, data)
            raise BlockNotFound(cid, "corrupted on disk and quarantined") from None
        return data

    def put(self, cid: CID, data: bytes | memoryview) -> bool:
        """Store one block after checking it; False when it was already here."""
        cid.verify(data)
        with self.stage() as staged:
            staged.add(cid, data)
            return staged.commit() > 0

    def stage(self) -> Staging:
        return Staging(self)

    def hold(self) -> Hold:
        return Hold(self)

    def _keep(self, hold: Hold, multihash: bytes, *, put: bool = False) -> bool:
        """Hold ``multihash`` if it is stored; ``put``: an upload that found it stored, which
        starts its grace period again."""
        with self._lock:
            if multihash not in self._index:
                return False
            self._hold_locked(hold, multihash)
            if put:
                self._put_again[multihash] = time.time()
            return True

    def _hold_locked(self, hold: Hold, multihash: bytes) -> None:
        """Count ``hold`` among the holders of ``multihash``; the caller has ``_lock``."""
        if multihash not in hold.held:
            hold.held.add(multihash)
            self._held[multihash] += 1

    def _release(self, hold: Hold) -> None:
        """Give back what ``hold`` held, in time linear in it (``Counter -=`` would walk every
        block every open hold holds)."""
        with self.sweeping, self._lock:
            for multihash in hold.held:
                remaining = self._held[multihash] - 1
                if remaining:
                    self._held[multihash] = remaining
                else:
                    del self._held[multihash]
            hold.held.clear()

    def usage(self) -> tuple[int, int]:
        """How many blocks are stored, and the bytes their packs take (dead bytes included)."""
        with self._lock:
            count = len(self._index)
            packs = list(self._members)
        return count, sum(_size_or_zero(self.pack_path(pack)) for pack in packs)

    def stored(self) -> list[StoredBlock]:
        with self._lock:
            return [
                StoredBlock(
                    multihash,
                    location.length,
                    max(self._committed[location.pack], self._put_again.get(multihash, 0.0)),
                )
                for multihash, location in self._index.items()
            ]

    def collect(self, multihashes: Iterable[bytes]) -> list[bytes]:
        """Delete the blocks no operation holds; returns those deleted."""
        with self._lock:
            unheld = [multihash for multihash in multihashes if multihash not in self._held]
            return self._delete(unheld)

    def delete(self, multihashes: Iterable[bytes]) -> None:
        """Forget blocks, held or not; their bytes stay in their packs until ``compact``."""
        with self._lock:
            self._delete(multihashes)

    def _delete(self, multihashes: Iterable[bytes]) -> list[bytes]:
        deleted: list[bytes] = []
        touched: set[str] = set()
        for multihash in multihashes:
            location = self._index.pop(multihash, None)
            self._put_again.pop(multihash, None)
            if location is not None:
                self._members[location.pack].pop(multihash, None)
                touched.add(location.pack)
                deleted.append(multihash)
        for pack in touched:
            self._write_index(pack)
        return deleted

    def compact(self, min_dead_fraction: float = 0.5) -> int:
        """Rewrite packs whose dead bytes reach the fraction; returns the bytes reclaimed."""
        reclaimed = 0
        for pack in list(self._members):
            with self._lock:
                live = dict(self._members.get(pack, {}))
            dead = self._dead_bytes(pack, live)
            worth_it = dead > 0 and dead >= min_dead_fraction * (dead + _length(live))
            if worth_it and self._rewrite(pack, live):
                reclaimed += dead
        return reclaimed

    def _dead_bytes(self, pack: str, live: dict[bytes, Location]) -> int:
        """Bytes of ``pack`` that ``live`` does not use; none when the pack is gone."""
        try:
            return self.pack_path(pack).stat().st_size - _length(live)
        except FileNotFoundError:
            return 0

    def _rewrite(self, pack: str, live: dict[bytes, Location]) -> bool:
        """Copy ``live`` into a new pack that replaces ``pack``; False when ``pack`` was gone.

        A pack goes when its last block is deleted (a quarantine) while it is being read:
        the copy then replaces nothing and ``_register`` drops it.
        """
        try:
            source = self.pack_path(pack).open("rb")
        except FileNotFoundError:
            return False
        with source, self.stage() as staged:
            for multihash, location in live.items():
                source.seek(location.offset)
                staged.write(multihash, source.read(location.length))
            staged.commit(replacing=pack)
        return True

    def _write_index(self, pack: str) -> None:
        members = self._members[pack]
        if not members:
            self._drop_pack(pack)
            return
        entries = [[key.hex(), loc.offset, loc.length] for key, loc in members.items()]
        atomic_write(self.packs / f"{pack}.idx", json.dumps(entries).encode())

    def _drop_pack(self, pack: str) -> None:
        """Forget an empty pack: its index goes first, so a crash leaves an uncommitted pack."""
        del self._members[pack]
        self._committed.pop(pack, None)
        (self.packs / f"{pack}.idx").unlink(missing_ok=True)
        fsync_dir(self.packs)
        self.pack_path(pack).unlink(missing_ok=True)

    def _register(
        self, pack: str, members: dict[bytes, Location], replacing: str | None, hold: Hold
    ) -> None:
        """Make a committed pack's blocks visible and held by ``hold``.

        An upload's block that another upload committed meanwhile is left out (and held, as
        the upload relies on it); so is a compaction's copy of a block deleted while it was
        copied, which would otherwise come back (every copy when the pack itself went).
        """
        with self._lock:
            if replacing is None:
                stale = members.keys() & self._index.keys()
                for multihash in stale:
                    self._hold_locked(hold, multihash)
            else:
                stale = members.keys() - self._members.get(replacing, {}).keys()
            for multihash in stale:
                del members[multihash]
            self._members[pack] = members
            self._committed[pack] = self._committed.get(replacing or "", time.time())
            self._index.update(members)
            for multihash in members:
                self._hold_locked(hold, multihash)
            if replacing in self._members:
                self._drop_pack(replacing)
            if stale:
                self._write_index(pack)

    def _quarantine(self, cid: CID, location: Location, data: bytes) -> None:
        target = self.quarantine / f"{cid.multihash.hex()}.{int(time.time())}"
        atomic_write(target, data)
        self.delete([cid.multihash])
        log.error(
            "corrupted block quarantined",
            extra={"cid": str(cid), "pack": location.pack, "file": str(target)},
        )
        if self.on_corrupt is not None:
            self.on_corrupt(cid, target)


class Hold:
    """Stored blocks an operation relies on, which garbage collection leaves until it closes."""

    def __init__(self, store: Blockstore) -> None:
        self.store = store
        self.held: set[bytes] = set()

    def __enter__(self) -> Hold:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def keep(self, cid: CID, *, put: bool = False) -> bool:
        """Hold ``cid``'s block if it is stored; False if it is not (or no longer) there.
        ``put``: an upload found it stored, which starts its grace period again."""
        return self.store._keep(self, cid.multihash, put=put)

    def close(self) -> None:
        self.store._release(self)


class Staging:
    """Blocks of one upload in a new pack, durable on disk but invisible until ``commit``.

    An upload that fails half-way (a truncated body, a bad block in a CAR) is discarded by
    leaving the context without committing: nothing of it ever appears in the store. Until
    then, and after a commit until it is discarded, it holds (``hold``) what it relies on:
    the stored blocks it did not write again, and those it committed.
    """

    def __init__(self, store: Blockstore) -> None:
        self.store = store
        self.name = f"{time.time_ns():020d}-{uuid.uuid4().hex[:8]}"
        self.path = store.pack_path(self.name)
        self.directory = store.spool
        self._file = self.path.open("xb")
        self._members: dict[bytes, Location] = {}
        self._offset = 0
        self.hold = store.hold()

    def __enter__(self) -> Staging:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.discard()

    def __contains__(self, cid: CID) -> bool:
        return cid.multihash in self._members

    @property
    def new_bytes(self) -> int:
        """Bytes of the blocks staged that the store did not hold: what a commit adds."""
        return self._offset

    def add(self, cid: CID, data: bytes | memoryview) -> None:
        """Stage a block the caller has already checked against ``cid``.

        An identity CID carries its block in itself and is answered from the CID, never
        looked up: it is not stored (kubo neither), so a CAR full of them costs no disk.
        """
        if cid.hash_code == IDENTITY:
            return
        if cid.multihash in self._members:
            return
        if not self.hold.keep(cid, put=True):
            self.write(cid.multihash, data)

    def write(self, multihash: bytes, data: bytes | memoryview) -> None:
        self._file.write(data)
        self._members[multihash] = Location(self.name, self._offset, len(data))
        self._offset += len(data)

    def get(self, cid: CID) -> bytes:
        location = self._members.get(cid.multihash)
        if location is None:
            return self.store.get(cid)
        self._file.flush()
        with self.path.open("rb") as pack:
            pack.seek(location.offset)
            return pack.read(location.length)

    def commit(self, replacing: str | None = None) -> int:
        """Make every staged block visible; returns how many were new."""
        committed = len(self._members)
        if self._file.closed:
            return 0
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        if not self._members:
            self.path.unlink()
            return 0
        entries = [[key.hex(), loc.offset, loc.length] for key, loc in self._members.items()]
        atomic_write(self.store.packs / f"{self.name}.idx", json.dumps(entries).encode())
        self.store._register(self.name, dict(self._members), replacing, self.hold)
        self._members.clear()
        return committed

    def discard(self) -> None:
        """Drop an uncommitted pack (once committed, only give back what it held)."""
        if not self._file.closed:
            self._file.close()
            self.path.unlink(missing_ok=True)
        self._members.clear()
        self.hold.close()


def remove_temporaries(directory: Path) -> None:
    """Remove what ``atomic_write`` left in ``directory`` when killed before its rename
    (``.<name>.<pid>.tmp``): called at start, when nothing writes, since nothing else
    would ever remove them."""
    for leftover in directory.glob(".*.tmp"):
        log.info("dropping a leftover temporary file", extra={"file": str(leftover)})
        leftover.unlink(missing_ok=True)


def _length(members: dict[bytes, Location]) -> int:
    return sum(location.length for location in members.values())


def _size_or_zero(path: Path) -> int:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0


def cid_for_multihash(multihash: bytes) -> CID:
    """The name kubo gives a stored block in listings: the store keeps no codec, so raw."""
    return CID(1, RAW, multihash)
