"""UnixFS directories: built as ``ipfs add -r`` builds them, listed, and walked by path.

A directory is a dag-pb node of UnixFS type Directory whose links, sorted by name bytes, are
its entries. When the entries would make the node too large, kubo (boxo) shards it into a HAMT
instead: nodes of type HAMTShard with a fanout of 256 by default (any power of two from 8 to
1,024 with ``Import.UnixFSHAMTDirectoryMaxFanout``), where an entry's bucket at each level is
the next log2(fanout) bits, most significant first, of the 64-bit murmur3 (x64, 128-bit
variant, first half) hash of its name: a whole byte at fanout 256, half a byte at 16. A bucket
holding one entry links to it under ``<hex bucket><name>``; a bucket holding several links to
a child shard under ``<hex bucket>`` alone, the bucket padded to the hex width of
``fanout - 1``. boxo never rehashes: a level past the hash's 64 bits is an error there, and
here. The layout depends on the set of names only, so building it from the final entries
gives kubo's CIDs.

The decision follows boxo: shard when the directory's estimated size exceeds 256 KiB (a
directory exactly at the threshold stays basic), estimated by default as kubo always has, the
sum over entries of ``len(name) + len(cid bytes)``, or, for the ``unixfs-v1-2025`` profile
(IPIP-499), as the exact size of the basic directory's block.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import mmh3

from robocloud.cid import CID, DAG_PB, Block
from robocloud.dagpb import Link, PBNode
from robocloud.unixfs import (
    DIRECTORY,
    HAMT_SHARD,
    MAX_DAG_DEPTH,
    MURMUR3_X64_64,
    GetBlock,
    UnixfsData,
    UnixfsError,
    decode_node,
    hamt_fanout_ok,
    hamt_prefix_width,
)

SHARDING_THRESHOLD = 256 * 1024
HAMT_FANOUT = 256
HASH_BITS = 64
"""The bits of a name's hash a HAMT may use: boxo's ``hashBits.Next`` refuses to read past them
(no rehash, unlike js-ipfs-unixfs), so neither building nor resolving goes deeper."""
MAX_NAME_BYTES = 255
"""What POSIX file systems allow for one path segment; longer names are refused."""


class PathError(UnixfsError):
    """A path that cannot be followed; ``segment`` is the one at fault, ``at`` where it failed."""

    def __init__(self, message: str, *, segment: str, at: CID) -> None:
        super().__init__(message)
        self.segment = segment
        self.at = at


class PathNotFound(PathError):
    """A segment that names no entry of its directory."""


class NotADirectory(PathError):
    """A segment asked of something that is not a directory (a file, a raw block)."""


def check_name(name: str) -> str:
    """An entry name as UnixFS allows it: one non-empty segment, not ``.`` or ``..``."""
    if name in ("", ".", "..") or "/" in name or "\x00" in name:
        raise UnixfsError(f"{name!r} is not a valid directory entry name")
    if len(name.encode()) > MAX_NAME_BYTES:
        raise UnixfsError(f"an entry name of more than {MAX_NAME_BYTES} bytes")
    return name


# ---- building ----


def directory_node(
    entries: list[Link], cid_version: int = 1, *, block_sized: bool = False
) -> tuple[list[Block], Link]:
    """The blocks of one directory over ``entries``, basic or sharded, and the link to it.

    The link's name is empty and its ``tsize`` is the whole directory's cumulative size.
    """
    names = [entry.name for entry in entries]
    if len(set(names)) != len(names):
        raise UnixfsError("a directory with two entries of the same name")
    for name in names:
        check_name(name)
    links = sorted(entries, key=lambda entry: entry.name.encode())
    data = UnixfsData(DIRECTORY)
    if block_sized:
        estimated = len(PBNode(links, data.encode()).encode())
    else:
        estimated = sum(len(entry.name.encode()) + len(entry.cid.binary) for entry in entries)
    if estimated > SHARDING_THRESHOLD:
        return sharded_directory(entries, cid_version)
    return _node(links, data, cid_version)


def _node(links: list[Link], data: UnixfsData, cid_version: int) -> tuple[list[Block], Link]:
    encoded = PBNode(links, data.encode()).encode()
    cid = CID.from_block(encoded, DAG_PB, cid_version)
    return [Block(cid, encoded)], Link(cid, "", len(encoded) + sum(link.tsize for link in links))


def name_hash(name: str) -> bytes:
    """The 8 bytes that place ``name`` in a HAMT: murmur3 x64 128's first half, big-endian."""
    first, _ = mmh3.hash64(name.encode(), seed=0, x64arch=True, signed=False)
    return int(first).to_bytes(8, "big")


def hash_slice(digest: int, consumed: int, bits: int) -> int:
    """The bucket of a name whose 64-bit hash is ``digest`` at a level that starts ``consumed``
    bits in: the next ``bits`` bits, most significant first, as boxo's ``hashBits.Next`` reads
    them (a slice may straddle two bytes, at fanout 8, 32 or 1,024)."""
    if consumed + bits > HASH_BITS:
        raise UnixfsError(
            f"a HAMT level of fanout {1 << bits} at bit {consumed} needs bits up to "
            f"{consumed + bits} of a name's {HASH_BITS}-bit hash; boxo reads no further "
            "(sharded directory too deep)"
        )
    return (digest >> (HASH_BITS - consumed - bits)) & ((1 << bits) - 1)


def _hash_of(name: str) -> int:
    return int.from_bytes(name_hash(name), "big")


def sharded_directory(
    entries: list[Link], cid_version: int = 1, *, fanout: int = HAMT_FANOUT
) -> tuple[list[Block], Link]:
    """A HAMT over ``entries`` whatever their size (kubo with sharding forced), deepest first.

    ``fanout`` is kubo's ``Import.UnixFSHAMTDirectoryMaxFanout`` (256 unless set), one the
    readers accept too; every shard of the HAMT has it, as boxo builds them.
    """
    if not hamt_fanout_ok(fanout):
        raise UnixfsError(f"a HAMT fanout {fanout} is not a power of two from 8 to 1,024")
    hashed = [(_hash_of(entry.name), entry) for entry in entries]
    blocks: list[Block] = []
    shape = _Shape(fanout, cid_version)
    return blocks, _build_shard(hashed, 0, shape, blocks)


@dataclass(frozen=True)
class _Shape:
    """What every shard of one HAMT shares."""

    fanout: int
    cid_version: int

    @property
    def bits(self) -> int:
        return self.fanout.bit_length() - 1

    def prefix(self, index: int) -> str:
        return f"{index:0{len(f'{self.fanout - 1:X}')}X}"


def _build_shard(
    hashed: list[tuple[int, Link]], consumed: int, shape: _Shape, blocks: list[Block]
) -> Link:
    """One shard (its children into ``blocks`` first) at ``consumed`` bits into the hashes."""
    if consumed + shape.bits > HASH_BITS:
        names = ", ".join(repr(entry.name) for _, entry in hashed)
        raise UnixfsError(
            f"the names {names} share the first {consumed} bits of their {HASH_BITS}-bit HAMT "
            f"hash; at fanout {shape.fanout} boxo cannot shard them"
        )
    buckets: dict[int, list[tuple[int, Link]]] = {}
    for item in hashed:
        buckets.setdefault(hash_slice(item[0], consumed, shape.bits), []).append(item)
    links: list[Link] = []
    for index in sorted(buckets):
        members = buckets[index]
        if len(members) == 1:
            entry = members[0][1]
            links.append(Link(entry.cid, shape.prefix(index) + entry.name, entry.tsize))
        else:
            child = _build_shard(members, consumed + shape.bits, shape, blocks)
            links.append(Link(child.cid, shape.prefix(index), child.tsize))
    occupied = sum(1 << index for index in buckets)
    # Big-endian without leading zero bytes, as go-bitfield writes it (boxo's encoding).
    bitfield = occupied.to_bytes((occupied.bit_length() + 7) // 8, "big")
    data = UnixfsData(HAMT_SHARD, bitfield, hash_type=MURMUR3_X64_64, fanout=shape.fanout)
    node_blocks, link = _node(links, data, shape.cid_version)
    blocks.extend(node_blocks)
    return link


@dataclass(frozen=True)
class BuiltDirectory:
    """One directory of a tree: the link to it and the blocks only it adds (HAMT shards too)."""

    link: Link
    blocks: list[Block]


class DirectoryBuilder:
    """Collects the files and directories of a tree, then builds every directory bottom-up.

    Paths are ``/``-separated and relative; a file's parent directories exist implicitly.
    """

    def __init__(self, cid_version: int = 1, *, block_sized_shards: bool = False) -> None:
        self.cid_version = cid_version
        self.block_sized_shards = block_sized_shards
        self._directories: set[tuple[str, ...]] = {()}
        self._files: dict[tuple[str, ...], Link] = {}

    def add_directory(self, path: str) -> None:
        parts = split_path(path)
        for depth in range(1, len(parts) + 1):
            self._directories.add(parts[:depth])

    def add_file(self, path: str, cid: CID, tsize: int) -> None:
        parts = split_path(path)
        if not parts:
            raise UnixfsError("a file needs a name")
        if parts in self._files:
            raise UnixfsError(f"{path!r} is given twice")
        self.add_directory("/".join(parts[:-1]))
        self._files[parts] = Link(cid, parts[-1], tsize)

    def finish(self) -> dict[str, BuiltDirectory]:
        """Every directory by path (the root is ``""``), built deepest first."""
        clash = self._directories & self._files.keys()
        if clash:
            raise UnixfsError(f"{'/'.join(min(clash))!r} is both a file and a directory")
        children: dict[tuple[str, ...], list[Link]] = {parts: [] for parts in self._directories}
        for parts, link in self._files.items():
            children[parts[:-1]].append(link)
        built: dict[str, BuiltDirectory] = {}
        for parts in sorted(self._directories, key=len, reverse=True):
            blocks, link = directory_node(
                children[parts], self.cid_version, block_sized=self.block_sized_shards
            )
            built["/".join(parts)] = BuiltDirectory(link, blocks)
            if parts:
                children[parts[:-1]].append(Link(link.cid, parts[-1], link.tsize))
        return built


def split_path(path: str) -> tuple[str, ...]:
    """The segments of a relative path; ``..``, ``.`` and empty segments are refused."""
    if path in ("", "."):
        return ()
    if path.startswith("/"):
        raise UnixfsError(f"{path!r} is not a relative path")
    parts = tuple(path.split("/"))
    if len(parts) > MAX_DAG_DEPTH:
        raise UnixfsError(f"a path deeper than {MAX_DAG_DEPTH} segments")
    return tuple(check_name(part) for part in parts)


# ---- reading ----


@dataclass(frozen=True)
class Resolved:
    """Where a path led: the target, and every block read on the way (for a CAR of the path)."""

    cid: CID
    path_blocks: list[CID]


def resolve(root: CID, segments: list[str], get_block: GetBlock) -> Resolved:
    """Follow ``segments`` from ``root`` through directories and HAMT shards."""
    visited: list[CID] = []
    current = root
    for segment in segments:
        visited.append(current)
        entry, shards = _find(current, segment, get_block)
        visited.extend(shards)
        current = entry
    return Resolved(current, visited)


def _find(directory: CID, name: str, get_block: GetBlock) -> tuple[CID, list[CID]]:
    """The CID ``name`` names in ``directory``, and the shard nodes read below its root."""
    if directory.codec != DAG_PB:
        raise NotADirectory(f"{directory} is not a directory", segment=name, at=directory)
    node, unixfs = decode_node(directory, get_block(directory))
    if unixfs.type == DIRECTORY:
        for link in node.links:
            if link.name == name:
                return link.cid, []
        raise PathNotFound(f"{directory} has no entry {name!r}", segment=name, at=directory)
    if unixfs.type != HAMT_SHARD:
        raise NotADirectory(f"{directory} is not a directory", segment=name, at=directory)
    return _find_insharded_directory(directory, node, unixfs, name, get_block)


def _find_insharded_directory(
    root: CID, node: PBNode, unixfs: UnixfsData, name: str, get_block: GetBlock
) -> tuple[CID, list[CID]]:
    """Descend from ``root`` as boxo's ``getValue`` does: each shard takes log2 of its own
    fanout in bits of the name's hash, and running out of the 64 bits is an error, not a miss.
    """
    digest = _hash_of(name)
    shards: list[CID] = []
    shard, consumed = root, 0
    while True:
        link, consumed = _bucket_link(shard, node, unixfs, digest, consumed)
        width = hamt_prefix_width(shard, unixfs)
        if link is None or (len(link.name) != width and link.name[width:] != name):
            raise PathNotFound(f"{root} has no entry {name!r}", segment=name, at=root)
        if len(link.name) != width:
            return link.cid, shards
        shard = link.cid
        shards.append(shard)
        node, unixfs = decode_node(shard, get_block(shard))
        if unixfs.type != HAMT_SHARD:
            raise UnixfsError(f"{shard} is linked as a HAMT shard but is not one")


def _bucket_link(
    shard: CID, node: PBNode, unixfs: UnixfsData, digest: int, consumed: int
) -> tuple[Link | None, int]:
    """The link of ``shard``'s bucket for ``digest`` (None if empty), and the bits consumed."""
    width = hamt_prefix_width(shard, unixfs)
    bits = (unixfs.fanout or 0).bit_length() - 1
    try:
        prefix = f"{hash_slice(digest, consumed, bits):0{width}X}"
    except UnixfsError as exc:
        raise UnixfsError(f"the HAMT shard {shard}: {exc}") from None
    link = next((link for link in node.links if link.name[:width] == prefix), None)
    return link, consumed + bits


def list_entries(directory: CID, get_block: GetBlock) -> Iterator[Link]:
    """The entries of a directory, basic or sharded (shards in link order, depth first).

    A HAMT whose shards repeat, or hold more links than their fanout, is refused: neither can
    come from a set of names, and a few shards that all link the same sub-shard would list
    256 to the power of their depth entries from a 37 KB CAR.
    """
    node, unixfs = decode_node(directory, get_block(directory))
    if unixfs.type == DIRECTORY:
        yield from node.links
        return
    if unixfs.type != HAMT_SHARD:
        raise NotADirectory(f"{directory} is not a directory", segment="", at=directory)
    _check_fanout(directory, node, unixfs)
    shards = {directory}
    # Each shard's links with its own bucket width: boxo reads every shard's fanout anew.
    stack: list[tuple[Iterator[Link], int]] = [
        (iter(node.links), hamt_prefix_width(directory, unixfs))
    ]
    while stack:
        link = next(stack[-1][0], None)
        width = stack[-1][1]
        if link is None:
            stack.pop()
        elif len(link.name) != width:
            yield Link(link.cid, link.name[width:], link.tsize)
        elif len(stack) > MAX_DAG_DEPTH:
            raise UnixfsError(f"the HAMT of {directory} is deeper than {MAX_DAG_DEPTH} levels")
        elif link.cid in shards:
            raise UnixfsError(f"the HAMT of {directory} links the shard {link.cid} twice")
        else:
            shards.add(link.cid)
            child, data = decode_node(link.cid, get_block(link.cid))
            if data.type != HAMT_SHARD:
                raise UnixfsError(f"{link.cid} is linked as a HAMT shard but is not one")
            _check_fanout(link.cid, child, data)
            stack.append((iter(child.links), hamt_prefix_width(link.cid, data)))


def _check_fanout(shard: CID, node: PBNode, unixfs: UnixfsData) -> None:
    """A shard boxo reads (``hamt_prefix_width``) with no more links than buckets."""
    hamt_prefix_width(shard, unixfs)
    if len(node.links) > (unixfs.fanout or 0):
        raise UnixfsError(
            f"the HAMT shard {shard} has {len(node.links)} links, more than its fanout "
            f"{unixfs.fanout}"
        )
