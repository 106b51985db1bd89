"""The content store: blocks, pins and peers behind the operations robots ask for.

Everything here is synchronous file work with no knowledge of HTTP; the routes run it in
worker threads. Failures are the exceptions below, each naming the CID at fault;
``services.cas.errors`` says how each is answered.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from robocloud.car import ByteSource, CarError, CarReader, write_car
from robocloud.cid import CID, DAG_PB, IDENTITY, RAW, Block
from robocloud.dagpb import Link
from robocloud.directory import PathError, Resolved, list_entries, resolve
from robocloud.unixfs import (
    FILE,
    LINKING_CODECS,
    RAW_TYPE,
    GetBlock,
    UnixfsError,
    decode_node,
    file_range_blocks,
    file_size,
    links_of,
    read_file,
    walk_dag,
)
from services.cas.blockstore import (
    BlockNotFound,
    Blockstore,
    CorruptionHook,
    Hold,
    Staging,
    cid_for_multihash,
    remove_temporaries,
)
from services.cas.peers import OutcomeHook, PeerFetcher
from services.cas.pins import PinQuotaExceeded, PinSet
from services.cas.shares import UNBOUNDED, RecentWrites, Share, WriteRateExceeded

log = logging.getLogger("robocloud.cas.store")

DAG_SCOPES = ("block", "entity", "all")
WALK_READ_BYTES = 256 * 1024 * 1024
"""Bytes of blocks one path resolution, or one directory listing, reads at most when its
caller brings no budget of its own (``BudgetedReads``): the directories and HAMT shards on
the way to a path's target, or the nodes and shards of a directory the gateway lists.

Neither is answered in proportion to what it reads: a path of 256 segments through
directories padded to 8 MiB (a CAR section's most) read and hashed 2 GiB, and the gateway's
page of a HAMT whose few shards carry megabytes each read them all, for an answer of a few
hundred bytes, again at every request. The file reader's budget covers only the file.
kubo's directories and shards are at most a few hundred KiB: 256 MiB (about half a second
of hashing) passes a path of 256 of the largest, or any directory of ``MAX_LISTED_ENTRIES``.
"""
READS = "reads"
"""The key under which ``ContentStore.read_fetches`` counts what reads fetched from peers."""
MAX_LISTED_ENTRIES = 100_000
"""Entries one directory listing (``ls``, the gateway's page, ``format=dag-json`` of a
shard) answers with: about 30 MB of HTML or 15 MB of JSON."""


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


class ReadBudgetExceeded(ValueError):
    """One request would read more bytes of blocks than ``BudgetedReads`` allows it;
    ``field`` names the parameter that asked for the reads, when one did (``ls``'s ``arg``)."""

    def __init__(self, cid: CID, limit: int, field: str | None = None) -> None:
        super().__init__(
            f"reading block {cid} would take this request past {limit} bytes of blocks read"
        )
        self.cid = cid
        self.limit = limit
        self.field = field


class TooManyEntries(ValueError):
    """A directory (a HAMT, whose shards may hold millions of names) with more entries than
    one listing answers."""

    def __init__(self, directory: CID, limit: int) -> None:
        super().__init__(f"{directory} has more than {limit} entries, more than one listing holds")
        self.directory = directory
        self.limit = limit


class UnpinnedArgument(ValueError):
    """A CID asked about in a pin listing that nobody pinned."""

    def __init__(self, cid: CID) -> None:
        super().__init__(f"{cid} is not pinned")
        self.cid = cid


@dataclass(frozen=True)
class WalkedDag:
    """One root of a request's walk over the DAGs it pins."""

    root: CID
    missing: CID | None
    """The first block that neither the store nor its peers have; None when the DAG is whole."""
    size: int
    """The DAG's cumulative size (kubo's ``CumulativeSize``, what ``add`` answers as
    ``Size``): its blocks' bytes, a sub-DAG linked twice counted twice; 0 when not whole."""


class WalkOverBudget(Exception):
    def __init__(self, walked: int) -> None:
        super().__init__(f"walked {walked} bytes, past the budget")
        self.walked = walked


class DagSizes:
    """The cumulative sizes of the DAGs one request walks, each root's on its own.

    The roots of a request share one walk, which reads a block under several of them once.
    Charging a pin only what the shared walk read first under its root let a robot pin a DAG
    and a part of it together, unpin the DAG and keep the part pinned for nothing. A root's
    size is rather its own DAG's, computed from every block's size and links recorded as the
    walk passes, each sub-DAG's once (``_sizes``): the work stays linear in the blocks.

    ``budget``: the bytes the walk may read before :class:`WalkOverBudget` stops it. The
    distinct bytes read are at most the sizes of the DAGs, so a walk past the room left in a
    robot's share is refused for certain: a pin's walk stops there rather than read the rest
    of a stored DAG of any size, or fetch it from the peers, first.
    """

    def __init__(self, budget: int | None = None) -> None:
        self.budget = budget
        self.walked = 0
        self._blocks: dict[CID, tuple[int, list[CID]]] = {}
        self._sizes: dict[CID, int] = {}

    def record(self, block: Block) -> None:
        own = _stored_size(block)
        self.walked += own
        if self.budget is not None and self.walked > self.budget:
            raise WalkOverBudget(self.walked)
        self._blocks[block.cid] = (own, [])

    def links(self, cid: CID, links: list[CID]) -> None:
        """``cid``'s links, as the walk that recorded it decoded them (``walk_dag``'s
        ``on_links``)."""
        self._blocks[cid] = (self._blocks[cid][0], links)

    def of(self, root: CID) -> int:
        """``root``'s cumulative size; every block under it must have been recorded."""
        stack = [(root, False)]
        while stack:
            cid, children_done = stack.pop()
            if cid in self._sizes:
                continue
            own, links = self._blocks[cid]
            if children_done:
                self._sizes[cid] = own + sum(self._sizes[link] for link in links)
            else:
                stack.append((cid, True))
                stack.extend((link, False) for link in links if link not in self._sizes)
        return self._sizes[root]


@dataclass(frozen=True)
class ImportedRoot:
    """A root of an imported CAR; ``pin_error`` says why it was not pinned, if it was not."""

    cid: CID
    pin_error: str


class ContentStore:
    def __init__(
        self,
        root: Path,
        blocks: Blockstore,
        peers: PeerFetcher | None = None,
        *,
        max_cached_bytes_per_hour: int | None = None,
        on_not_kept: Callable[[CID], None] | None = None,
    ) -> None:
        remove_temporaries(root)
        self.blocks = blocks
        self.peers = peers
        self.pins = PinSet(root / "pins.log", dag_bytes=self._stored_dag_bytes)
        self.writes = RecentWrites()
        self.read_fetches = RecentWrites()
        """The bytes reads fetched from peers and kept, in a rolling hour (one count,
        :data:`READS`): at most ``max_cached_bytes_per_hour``, past which a block fetched
        for a read is served without being kept."""
        self.max_cached_bytes_per_hour = max_cached_bytes_per_hour
        self.on_not_kept = on_not_kept
        """Told of each block a read fetched and served without keeping it (a metric)."""
        self.collecting = threading.Lock()
        """Held by a whole collection, compaction included: the periodic one and ``repo/gc``
        ran at once, both rewrote the same pack, and the one that found it gone failed."""

    @classmethod
    def open(
        cls,
        root: Path,
        peers: list[str],
        *,
        peer_timeout_s: float = 10.0,
        max_cached_bytes_per_hour: int | None = None,
        on_corrupt: CorruptionHook | None = None,
        on_peer_outcome: OutcomeHook | None = None,
        on_not_kept: Callable[[CID], None] | None = None,
    ) -> ContentStore:
        """The store under ``root``, fetching missing blocks from ``peers`` (gateway URLs)."""
        fetcher = None
        if peers:
            fetcher = PeerFetcher(peers, timeout_s=peer_timeout_s, on_outcome=on_peer_outcome)
        return cls(
            root,
            Blockstore(root, on_corrupt=on_corrupt),
            fetcher,
            max_cached_bytes_per_hour=max_cached_bytes_per_hour,
            on_not_kept=on_not_kept,
        )

    def check_writable(self) -> None:
        """Raise ``OSError`` unless the pack directory is there (a readiness check)."""
        self.blocks.packs.stat()

    def usage(self) -> tuple[int, int]:
        """Blocks stored, and the bytes their packs take on disk."""
        return self.blocks.usage()

    # ---- blocks ----

    def get_block(
        self,
        cid: CID,
        *,
        use_peers: bool = True,
        charge_fetched: Callable[[int], None] | None = None,
    ) -> bytes:
        """A verified block: inline in an identity CID, local, else from a peer (then kept,
        see :meth:`_keep_fetched`).

        An identity CID carries its block in its multihash (at most 128 bytes, bounded when the
        CID is parsed): it is answered from the CID itself, never looked up or stored.
        """
        if cid.hash_code == IDENTITY:
            return cid.digest
        try:
            return self.blocks.get(cid)
        except BlockNotFound as miss:
            reason = miss.reason
        if use_peers and self.peers is not None:
            data = self.peers.fetch(cid)
            if data is not None:
                self._keep_fetched(cid, data, charge_fetched)
                return data
            reason += "; no peer has it"
        raise BlockUnavailable(cid, reason)

    def _keep_fetched(self, cid: CID, data: bytes, charge: Callable[[int], None] | None) -> None:
        """Store a block fetched from a peer. A pin's walk charges it to the robot's new
        bytes of the hour first (``charge``, which raises past them: a robot pinning and
        unpinning DAGs at the peers wrote without bound). A read keeps it while what reads
        fetched in the hour fits ``max_cached_bytes_per_hour``, and past that serves it
        without keeping it: any stranger chooses what a read fetches, and every read kept
        until the next collection let one fill the disk with the peers' content."""
        if charge is not None:
            charge(len(data))
        else:
            try:
                self.read_fetches.add(READS, len(data), self.max_cached_bytes_per_hour)
            except WriteRateExceeded:
                if self.on_not_kept is not None:
                    self.on_not_kept(cid)
                return
        self.blocks.put(cid, data)

    def block_size(self, cid: CID, *, use_peers: bool = True) -> int:
        if cid.hash_code == IDENTITY:
            return len(cid.digest)
        if self.blocks.has(cid):
            return self.blocks.size(cid)
        return len(self.get_block(cid, use_peers=use_peers))

    def put_blocks(
        self,
        blocks: list[bytes],
        codec: int,
        owner: str,
        *,
        pin: bool,
        share: Share = UNBOUNDED,
    ) -> list[CID]:
        """Store raw blocks as one pack (one fsync, all or none), then pin them if asked.

        A pin keeps a whole DAG, so with ``pin`` every block's DAG must be complete, as for
        ``pin/add``, but from this request's blocks and the store's alone, as kubo's import
        asks no peer: a block neither has refuses the request (``DagIncomplete``) with
        nothing stored, as does ``owner``'s ``share`` (``commit_within``).
        """
        cids = [CID.from_block(data, codec, 1) for data in blocks]
        with self.blocks.stage() as staging:
            for cid, data in zip(cids, blocks, strict=True):
                staging.add(cid, data)
            charges = {}
            if pin:
                walked = self.walked_to_pin(cids, owner, share, staging, use_peers=False)
                charges = _whole(walked)
            self.commit_within(staging, charges, owner, share)
        return cids

    def commit_within(
        self, staging: Staging, charges: dict[CID, int], owner: str, share: Share
    ) -> None:
        """Store what ``staging`` holds and pin the roots of ``charges`` for ``owner``, within
        its ``share``: past either bound (``PinQuotaExceeded``, ``WriteRateExceeded``)
        nothing is stored. Two requests of one robot may both pass the pin check before
        either pins; the second is then refused after its blocks are stored, pinned by
        nobody, for the next collection past the grace period."""
        self.pins.check_share(charges, owner, max_bytes=share.max_pinned_bytes)
        with self.writes.charge(owner, staging.new_bytes, share.max_written_bytes_per_hour):
            staging.commit()
        if charges:
            self.pins.add_all(charges, owner, max_bytes=share.max_pinned_bytes)

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

    # ---- directories and paths ----

    def _getter(self, use_peers: bool, get: GetBlock | None) -> GetBlock:
        """``get`` when the caller reads through its own budget (``ls``'s ``BudgetedReads``),
        else the store's blocks within a budget of ``WALK_READ_BYTES`` for this one call."""
        return get or BudgetedReads.walk(self, use_peers=use_peers).get

    def resolve(
        self,
        root: CID,
        segments: list[str],
        *,
        use_peers: bool = True,
        get: GetBlock | None = None,
    ) -> Resolved:
        """Follow a content path through directories and HAMT shards."""
        try:
            return resolve(root, segments, self._getter(use_peers, get))
        except PathError:
            raise
        except UnixfsError as exc:
            raise InvalidDag(root, str(exc)) from exc

    def entries(
        self, directory: CID, *, use_peers: bool = True, get: GetBlock | None = None
    ) -> list[Link]:
        """A directory's entries (a sharded one's from every shard); ``NotADirectory`` else,
        and ``TooManyEntries`` past ``MAX_LISTED_ENTRIES``, before its other shards are read:
        each entry costs a few hundred bytes of memory and of answer."""
        try:
            found = list(
                itertools.islice(
                    list_entries(directory, self._getter(use_peers, get)), MAX_LISTED_ENTRIES + 1
                )
            )
        except PathError:
            raise
        except UnixfsError as exc:
            raise InvalidDag(directory, str(exc)) from exc
        if len(found) > MAX_LISTED_ENTRIES:
            raise TooManyEntries(directory, MAX_LISTED_ENTRIES)
        return found

    def kind(self, cid: CID, *, use_peers: bool = True, get: GetBlock | None = None) -> UnixfsKind:
        """What a CID names, from its root block: a file, a directory, or another block.

        A raw block is a file of its own length, which the block index holds: it is not read
        (``ls`` of 65,536 links to one 8 MiB raw block read and re-hashed it per entry).
        """
        if cid.codec == RAW:
            return UnixfsKind(FILE, self.block_size(cid, use_peers=use_peers))
        if cid.codec != DAG_PB:
            return UnixfsKind(None, None)
        try:
            _, unixfs = decode_node(cid, self._getter(use_peers, get)(cid))
        except UnixfsError:
            return UnixfsKind(None, None)
        if unixfs.type in (FILE, RAW_TYPE):
            return UnixfsKind(FILE, len(unixfs.data) + sum(unixfs.blocksizes))
        return UnixfsKind(unixfs.type, None)

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

    def export_path_car(
        self,
        root: CID,
        resolved: Resolved,
        scope: str,
        entity_bytes: tuple[int, int | None] | None = None,
        *,
        use_peers: bool = True,
    ) -> Iterator[bytes]:
        """A CAR of a path: the blocks that verify each segment, then the target's scope.

        ``entity_bytes`` (``[start, end)``, already resolved against the file's size) is given
        for a target the caller found to be a file, which contributes only the blocks covering
        those bytes. The caller worked out the target's kind on a worker thread: this call
        runs on the event loop, where reading and hashing the target's block (or fetching it
        from a peer) held every route.
        """
        get = partial(self.get_block, use_peers=use_peers)
        if entity_bytes is not None:
            target: Iterator[Block] = self._range_blocks(resolved.cid, get, entity_bytes)
        else:
            target = self.blocks_of(resolved.cid, scope, use_peers=use_peers)
        path = (Block(cid, get(cid)) for cid in resolved.path_blocks)
        return write_car([root], _once(path, target))

    @staticmethod
    def _range_blocks(
        root: CID, get: Callable[[CID], bytes], span: tuple[int, int | None]
    ) -> Iterator[Block]:
        """The blocks covering ``span`` of the file ``root``; a DAG the reader refuses (too
        deep, lying sizes, over its visit budget) is an ``InvalidDag`` as in any other CAR."""
        try:
            yield from file_range_blocks(root, get, *span)
        except UnixfsError as exc:
            raise InvalidDag(root, str(exc)) from exc

    def import_car(
        self,
        staging: Staging,
        source: ByteSource,
        check_roots: Callable[[list[CID]], None] | None = None,
        on_block: Callable[[Block], None] | None = None,
    ) -> list[CID]:
        """Stage every block of a CAR; any bad block raises and the caller discards it all.

        ``check_roots`` sees the header's roots before any block is read, and may refuse them
        by raising: an import over many CARs bounds its roots before it hashes their blocks.
        ``on_block`` sees each block section, verified, as it is staged.
        """
        try:
            reader = CarReader(source)
            if check_roots is not None:
                check_roots(reader.roots)
            for block in reader:
                if on_block is not None:
                    on_block(block)
                staging.add(block.cid, block.data)
        except CarError as exc:
            raise CarRejected(str(exc)) from exc
        return reader.roots

    def missing_block(
        self, root: CID, staging: Staging | None = None, *, hold: Hold | None = None
    ) -> CID | None:
        """The first block of ``root``'s DAG that neither the store nor its peers have.

        ``hold`` (the staging's by default) keeps every stored block read from garbage
        collection.
        """
        return self._walk(root, staging, hold=hold).missing

    def _walk(
        self,
        root: CID,
        staging: Staging | None = None,
        *,
        seen: set[CID] | None = None,
        hold: Hold | None = None,
        sizes: DagSizes | None = None,
        get: GetBlock | None = None,
    ) -> WalkedDag:
        """``root``'s DAG walked. ``seen``: blocks whose DAGs earlier walks of this request
        found complete, not read again, each recorded in ``sizes``. ``get`` reads a block
        that is not staged (by default the store's or a peer's, as a read)."""
        keeper = hold or (staging.hold if staging is not None else None)
        get = partial(
            self._staged_or_stored, staging=staging, hold=keeper, get=get or self.get_block
        )
        sizes = sizes or DagSizes()
        try:
            for block in walk_dag(root, get, "all", seen, sizes.links):
                sizes.record(block)
        except _Missing as missing:
            return WalkedDag(root, missing.cid, 0)
        except UnixfsError as exc:
            raise InvalidDag(root, str(exc)) from exc
        return WalkedDag(root, None, sizes.of(root))

    def _stored_dag_bytes(self, root: CID) -> int:
        """The cumulative size of ``root``'s DAG stored here, asking no peer: the charge of a
        pin read from a journal written before pins were charged (a pinned DAG is whole
        here; one that is not is charged nothing, and said)."""
        try:
            walked = self._walk(root, get=partial(self.get_block, use_peers=False))
        except InvalidDag as exc:
            log.warning("pinned DAG not valid", extra={"cid": str(root), "error": str(exc)})
            return 0
        if walked.missing is not None:
            log.warning(
                "pinned DAG not whole here",
                extra={"cid": str(root), "missing": str(walked.missing)},
            )
        return walked.size

    @staticmethod
    def _staged_or_stored(
        cid: CID, staging: Staging | None, hold: Hold | None, get: GetBlock
    ) -> bytes:
        if staging is not None and cid in staging:
            return staging.get(cid)
        if hold is None or cid.hash_code == IDENTITY:
            return _stored(cid, get)
        held = hold.keep(cid)  # before the read: no collection between the two
        data = _stored(cid, get)
        if not held and not hold.keep(cid):
            raise _Missing(cid)  # fetched from a peer, then collected before it was held
        return data

    # ---- pins and garbage collection ----

    def pin(self, roots: list[CID], owner: str, *, share: Share = UNBOUNDED) -> None:
        """Pin DAGs for ``owner``, all or none, once every block of each is here (fetched from
        peers if need be) and they fit its ``share`` of pins: a request refused for one root
        leaves no pin behind, as ``unpin``."""
        with self.blocks.hold() as hold:
            charges = _whole(self.walked_to_pin(roots, owner, share, hold=hold))
            self.pins.add_all(charges, owner, max_bytes=share.max_pinned_bytes)

    def walked_to_pin(
        self,
        roots: list[CID],
        owner: str,
        share: Share,
        staging: Staging | None = None,
        *,
        hold: Hold | None = None,
        use_peers: bool = True,
    ) -> Iterator[WalkedDag]:
        """The DAGs of the roots ``owner`` does not pin yet, walked as they are asked for
        (its pins need no walk: their DAGs were whole and valid when pinned), within the
        room left in its ``share``: the walk stops once it has read more than that
        (``PinQuotaExceeded``), rather than read a stored DAG of any size, or fetch one
        from the peers, first. With ``use_peers``, every block fetched is charged to the
        robot's new bytes of the hour (``WriteRateExceeded`` past them).

        The stop counts every distinct block read, also under a root found incomplete, which
        is charged nothing: an import of many partial DAGs may be refused a little early.
        """
        limit = share.max_pinned_bytes
        new = [root for root in dict.fromkeys(roots) if owner not in self.pins.owners(root)]
        used = self.pins.pinned_bytes(owner)
        sizes = DagSizes(None if limit is None else limit - used)
        get = partial(self.get_block, use_peers=False)
        if use_peers:
            charge = partial(self.writes.add, owner, limit=share.max_written_bytes_per_hour)
            get = partial(self.get_block, charge_fetched=charge)
        try:
            yield from self._walked_dags(new, staging, hold=hold, sizes=sizes, get=get)
        except WalkOverBudget as over:
            assert limit is not None, "only a bounded walk has a budget"
            raise PinQuotaExceeded(owner, over.walked, used, limit) from None

    def _walked_dags(
        self,
        roots: list[CID],
        staging: Staging | None = None,
        *,
        hold: Hold | None = None,
        sizes: DagSizes | None = None,
        get: GetBlock | None = None,
    ) -> Iterator[WalkedDag]:
        """Each distinct root's DAG walked, as it is asked for, with its cumulative size.

        One ``seen`` set for all roots: a sub-DAG that several roots share (every block of a
        ``block/put`` is a root; a CAR may name one DAG under its 1,024 header roots) is
        walked once, so the work stays linear in the blocks; ``DagSizes`` still gives each
        root its whole DAG's size.
        """
        seen: set[CID] = set()
        sizes = sizes or DagSizes()
        for root in dict.fromkeys(roots):
            yield self._walk(root, staging, seen=seen, hold=hold, sizes=sizes, get=get)

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
        """Remove every unpinned block put more than ``grace_s`` ago; never a block of a
        pinned DAG.

        The grace period protects blocks a robot pushed with ``block/put`` before pinning the
        root that links them, counted from the last put, since the block may have been stored
        long before by another robot. Pins run beside a collection: the blocks a pin check
        read or an upload relied on are held until the pin is there (``blockstore.Hold``),
        and the last phase, under ``sweeping``, marks the pins made since the first snapshot
        before it deletes, so a DAG pinned meanwhile loses nothing.

        One collection runs at a time (``collecting``): a second waits for the running one,
        then makes its own, which sees the pins removed meanwhile; joining the running one
        would have answered a robot that unpinned just before with what an older snapshot
        of the pins left collectable.
        """
        with self.collecting:
            return self._collect(cutoff=(time.time() if now is None else now) - grace_s)

    def _collect(self, cutoff: float) -> list[CID]:
        """Mark, delete the unmarked blocks put before ``cutoff``, compact."""
        visited: set[tuple[int, bytes]] = set()
        live: set[bytes] = set()
        pinned = self.pins.snapshot()
        for root in pinned:
            self._mark_reachable(root, visited, live)
        with self.blocks.sweeping:
            for root in self.pins.snapshot().keys() - pinned.keys():
                self._mark_reachable(root, visited, live)
            dead = self.blocks.collect(
                stored.multihash
                for stored in self.blocks.stored()
                if stored.multihash not in live and stored.put_at < cutoff
            )
        self.blocks.compact()
        return [cid_for_multihash(multihash) for multihash in dead]

    def _mark_reachable(self, root: CID, visited: set[tuple[int, bytes]], live: set[bytes]) -> None:
        """Add to ``live`` the multihash of every stored block under ``root``.

        Goes on past missing or corrupt blocks, so an incomplete pinned DAG loses nothing.
        Blocks are stored by multihash, but what a block links to depends on the codec its
        CID names: the same bytes are a leaf as ``raw`` and a node with links as ``dag-pb``.
        So the walk remembers ``(codec, multihash)``: a raw alias met first (in this pin or
        another robot's) never hides the links of the dag-pb CID. An identity CID carries its
        block: decoded in place, its links followed, and nothing of it is stored to keep.
        """
        stack = [root]
        while stack:
            cid = stack.pop()
            if (cid.codec, cid.multihash) in visited:
                continue
            visited.add((cid.codec, cid.multihash))
            if cid.hash_code == IDENTITY:
                data = cid.digest
            else:
                live.add(cid.multihash)
                if cid.codec not in LINKING_CODECS:
                    continue
                try:
                    data = self.blocks.get(cid)
                except BlockNotFound:
                    log.warning("pinned DAG incomplete during gc", extra={"cid": str(cid)})
                    continue
            try:
                stack.extend(links_of(cid, data))
            except UnixfsError:
                log.warning("pinned block does not decode during gc", extra={"cid": str(cid)})

    def close(self) -> None:
        self.pins.close()
        if self.peers is not None:
            self.peers.close()


def _stored(cid: CID, get: GetBlock) -> bytes:
    try:
        return get(cid)
    except BlockUnavailable:
        raise _Missing(cid) from None


def _whole(walked: Iterable[WalkedDag]) -> dict[CID, int]:
    """Each root with the bytes its pin is charged; ``DagIncomplete`` for the first root
    whose DAG lacks a block, before the walk of the next."""
    charges = {}
    for dag in walked:
        if dag.missing is not None:
            raise DagIncomplete(dag.root, dag.missing)
        charges[dag.root] = dag.size
    return charges


def _stored_size(block: Block) -> int:
    """What a block takes in the store: nothing for an identity CID, which carries it."""
    return 0 if block.cid.hash_code == IDENTITY else len(block.data)


def _once(first: Iterator[Block], rest: Iterator[Block]) -> Iterator[Block]:
    """``first`` then ``rest``, each block once (a path may pass a block the target repeats)."""
    seen: set[CID] = set()
    for block in itertools.chain(first, rest):
        if block.cid not in seen:
            seen.add(block.cid)
            yield block


class BudgetedReads:
    """The block reads of one request, at most ``limit`` bytes in all, and the ``kind`` of
    each CID worked out once.

    ``ls`` reads a block per entry for its type and size: a directory node of 65,536 links
    to one 8 MiB block cost minutes of re-hashing per ``arg``, free for anyone to ask. Each
    block's size comes from the index before it is read, so the read that would pass the
    budget is refused (``ReadBudgetExceeded``) rather than done.
    """

    def __init__(
        self,
        store: ContentStore,
        limit: int,
        *,
        use_peers: bool = True,
        field: str | None = None,
    ) -> None:
        self._store = store
        self._limit = limit
        self._use_peers = use_peers
        self._field = field
        self._kinds: dict[CID, UnixfsKind] = {}
        self.spent = 0
        self.listed = 0

    @classmethod
    def walk(
        cls, store: ContentStore, *, use_peers: bool = True, field: str | None = None
    ) -> BudgetedReads:
        """The reads of one path resolution or one listing: ``WALK_READ_BYTES``."""
        return cls(store, WALK_READ_BYTES, use_peers=use_peers, field=field)

    def get(self, cid: CID) -> bytes:
        """A verified block, charged to the budget by the size the index gives."""
        size = self._store.block_size(cid, use_peers=self._use_peers)
        if self.spent + size > self._limit:
            raise ReadBudgetExceeded(cid, self._limit, self._field)
        self.spent += size
        return self._store.get_block(cid, use_peers=self._use_peers)

    def resolve(self, root: CID, segments: list[str]) -> Resolved:
        return self._store.resolve(root, segments, get=self.get)

    def entries(self, directory: CID) -> list[Link]:
        """``ContentStore.entries``, at most ``MAX_LISTED_ENTRIES`` over the request."""
        found = self._store.entries(directory, get=self.get)
        self.listed += len(found)
        if self.listed > MAX_LISTED_ENTRIES:
            raise TooManyEntries(directory, MAX_LISTED_ENTRIES)
        return found

    def kind(self, cid: CID) -> UnixfsKind:
        """``ContentStore.kind``, remembered: entries that repeat a CID read its block once."""
        known = self._kinds.get(cid)
        if known is None:
            known = self._kinds[cid] = self._store.kind(cid, get=self.get)
        return known


@dataclass(frozen=True)
class UnixfsKind:
    """A UnixFS type (``FILE`` for raw blocks too) and, for a file, its declared size."""

    type: int | None
    size: int | None


class _Missing(Exception):
    def __init__(self, cid: CID) -> None:
        super().__init__(str(cid))
        self.cid = cid
