"""UnixFS over dag-pb: the importer that gives a file its IPFS CID, and the reader.

The importer reproduces ``ipfs add``: fixed-size chunks, a balanced tree with at most
``max_links`` links per node, raw leaves with CIDv1. It is incremental (``feed`` and
``finish``) so a server can hash an upload while it streams in, holding one chunk plus one
pending link list per tree level. The reader streams a file's bytes, or a byte range of them,
touching only the blocks the range needs (UnixFS ``blocksizes`` say where each child starts).
"""

from __future__ import annotations

import io
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import BinaryIO, NamedTuple

from robocloud.cid import CID, DAG_PB, RAW, Block, decode_varint
from robocloud.dagpb import DagPbError, Link, PBNode, fields, len_field, uint_field
from robocloud.errors import FormatError

DEFAULT_CHUNK_SIZE = 262_144
DEFAULT_MAX_LINKS = 174
MAX_CHUNK_SIZE = 2 * 1024 * 1024
MAX_DAG_DEPTH = 1024
"""Deepest path a walk or read follows. Importers stay far below it (a balanced 174-link tree
of 1 TiB is 4 levels deep, trickle layouts and HAMT shards a few dozen, directories as deep as
paths nest, and Linux's PATH_MAX of 4096 bytes allows at most 2048); a chain built to be deep
is refused instead of followed."""
PROFILES: dict[str, tuple[int, int, bool, int, bool]] = {
    # name: (cid_version, chunk size, raw leaves, max links, shard by exact block size)
    "unixfs-v0-2015": (0, DEFAULT_CHUNK_SIZE, False, DEFAULT_MAX_LINKS, False),
    "unixfs-v1-2025": (1, 1_048_576, True, 1024, True),
}

# UnixFS Data.Type
RAW_TYPE, DIRECTORY, FILE, METADATA, SYMLINK, HAMT_SHARD = range(6)


class UnixfsError(FormatError):
    """Bad import parameters, or a block that is not valid dag-pb/UnixFS."""


GetBlock = Callable[[CID], bytes]


@dataclass(frozen=True)
class ImportParams:
    """How files and directories become blocks. ``block_sized_shards`` picks IPIP-499's exact
    block-size estimate for the HAMT threshold over kubo's legacy name-plus-CID estimate."""

    cid_version: int = 1
    raw_leaves: bool = True
    chunk_size: int = DEFAULT_CHUNK_SIZE
    max_links: int = DEFAULT_MAX_LINKS
    block_sized_shards: bool = False

    def __post_init__(self) -> None:
        if self.cid_version not in (0, 1):
            raise UnixfsError(f"cid-version must be 0 or 1, not {self.cid_version}")
        if not 1 <= self.chunk_size <= MAX_CHUNK_SIZE:
            raise UnixfsError(f"chunk size must be between 1 and {MAX_CHUNK_SIZE} bytes")
        if self.max_links < 2:
            raise UnixfsError("a node needs room for at least 2 links")

    @classmethod
    def from_options(
        cls,
        cid_version: int | None = None,
        raw_leaves: bool | None = None,
        chunker: str | None = None,
        profile: str | None = None,
    ) -> ImportParams:
        """kubo's semantics: ``--cid-version=1`` implies raw leaves unless said otherwise."""
        version, chunk, raw, links, exact = 0, DEFAULT_CHUNK_SIZE, False, DEFAULT_MAX_LINKS, False
        if profile is not None:
            if profile not in PROFILES:
                raise UnixfsError(f"unknown profile {profile!r}; known: {', '.join(PROFILES)}")
            version, chunk, raw, links, exact = PROFILES[profile]
        if cid_version is not None:
            version = cid_version
            raw = raw or cid_version == 1
        if raw_leaves is not None:
            raw = raw_leaves
        if chunker is not None:
            chunk = parse_chunker(chunker)
        return cls(version, raw, chunk, links, exact)


def parse_chunker(chunker: str) -> int:
    """``size-N`` is the only chunker supported (rabin and buzhash are not)."""
    name, _, size = chunker.partition("-")
    if name != "size" or not size.isdigit():
        raise UnixfsError(f"unsupported chunker {chunker!r}: expected size-<bytes>")
    value = int(size)
    if not 1 <= value <= MAX_CHUNK_SIZE:
        raise UnixfsError(f"chunker size must be between 1 and {MAX_CHUNK_SIZE} bytes")
    return value


@dataclass
class UnixfsData:
    """The UnixFS ``Data`` message; ``hash_type`` and ``fanout`` belong to HAMT shards."""

    type: int
    data: bytes = b""
    filesize: int | None = None
    blocksizes: list[int] = field(default_factory=list)
    hash_type: int | None = None
    fanout: int | None = None

    def encode(self) -> bytes:
        out = uint_field(1, self.type)
        if self.data:
            out += len_field(2, self.data)
        if self.filesize is not None:
            out += uint_field(3, self.filesize)
        for size in self.blocksizes:
            out += uint_field(4, size)
        if self.hash_type is not None:
            out += uint_field(5, self.hash_type)
        if self.fanout is not None:
            out += uint_field(6, self.fanout)
        return out

    @classmethod
    def decode(cls, raw: bytes) -> UnixfsData:
        try:
            return cls._decode(raw)
        except (DagPbError, ValueError) as exc:
            raise UnixfsError(f"invalid UnixFS data: {exc}") from exc

    @classmethod
    def _decode(cls, raw: bytes) -> UnixfsData:
        node = cls(type=-1)
        for number, value in fields(raw):
            if number == 1 and isinstance(value, int):
                node.type = value
            elif number == 2 and isinstance(value, bytes):
                node.data = value
            elif number == 3 and isinstance(value, int):
                node.filesize = value
            elif number == 4 and isinstance(value, int):
                node.blocksizes.append(value)
            elif number == 4 and isinstance(value, bytes):  # packed encoding
                pos = 0
                while pos < len(value):
                    size, pos = decode_varint(value, pos)
                    node.blocksizes.append(size)
            elif number == 5 and isinstance(value, int):
                node.hash_type = value
            elif number == 6 and isinstance(value, int):
                node.fanout = value
        if node.type < 0:
            raise UnixfsError("UnixFS data without a type")
        return node


# ---- importer ----


@dataclass
class _Child:
    cid: CID
    tsize: int
    filesize: int


class Importer:
    """Turns a byte stream into UnixFS blocks, exactly as ``ipfs add`` does.

    A child is appended to level ``k``; when that level already holds ``max_links`` children,
    they first become one node appended to level ``k + 1``. Flushing only when another child
    arrives yields go-unixfs's balanced layout: full subtrees on the left, the file's tail on
    the right spine.
    """

    def __init__(self, params: ImportParams | None = None) -> None:
        self.params = params or ImportParams()
        self._buffer = bytearray()
        self._levels: list[list[_Child]] = [[]]
        self._size = 0
        self._finished = False

    def feed(self, data: bytes | memoryview) -> list[Block]:
        if self._finished:
            raise UnixfsError("importer already finished")
        blocks: list[Block] = []
        size = self.params.chunk_size
        view = memoryview(data)
        if self._buffer:
            missing = size - len(self._buffer)
            self._buffer += view[:missing]
            view = view[missing:]
            if len(self._buffer) < size:
                return blocks
            self._leaf(bytes(self._buffer), blocks)
            self._buffer.clear()
        whole = len(view) - len(view) % size
        for start in range(0, whole, size):
            self._leaf(bytes(view[start : start + size]), blocks)
        self._buffer += view[whole:]
        return blocks

    def finish(self) -> tuple[list[Block], CID, int]:
        """The remaining blocks, the root CID and the file size."""
        if self._finished:
            raise UnixfsError("importer already finished")
        self._finished = True
        blocks: list[Block] = []
        if self._buffer or self._size == 0:
            self._leaf(bytes(self._buffer), blocks)
            self._buffer.clear()
        level = 0
        while True:
            children = self._levels[level]
            if level == len(self._levels) - 1 and len(children) == 1:
                return blocks, children[0].cid, self._size
            self._append(level + 1, self._node(children, blocks), blocks)
            level += 1

    def _leaf(self, chunk: bytes, blocks: list[Block]) -> None:
        self._size += len(chunk)
        if self.params.raw_leaves:
            cid = CID.from_block(chunk, RAW, 1)
            block = Block(cid, chunk)
        else:
            unixfs = UnixfsData(FILE, chunk, len(chunk))
            encoded = PBNode([], unixfs.encode()).encode()
            block = Block(CID.from_block(encoded, DAG_PB, self.params.cid_version), encoded)
        blocks.append(block)
        self._append(0, _Child(block.cid, len(block.data), len(chunk)), blocks)

    def _append(self, level: int, child: _Child, blocks: list[Block]) -> None:
        if level == len(self._levels):
            self._levels.append([])
        if len(self._levels[level]) == self.params.max_links:
            self._append(level + 1, self._node(self._levels[level], blocks), blocks)
            self._levels[level] = []
        self._levels[level].append(child)

    def _node(self, children: list[_Child], blocks: list[Block]) -> _Child:
        sizes = [child.filesize for child in children]
        unixfs = UnixfsData(FILE, b"", sum(sizes), sizes)
        links = [Link(child.cid, "", child.tsize) for child in children]
        encoded = PBNode(links, unixfs.encode()).encode()
        cid = CID.from_block(encoded, DAG_PB, self.params.cid_version)
        blocks.append(Block(cid, encoded))
        tsize = len(encoded) + sum(child.tsize for child in children)
        return _Child(cid, tsize, sum(sizes))


def import_bytes(data: bytes, params: ImportParams | None = None) -> tuple[list[Block], CID]:
    """Import a whole byte string at once (small files, tests)."""
    importer = Importer(params)
    blocks = importer.feed(data)
    tail, root, _ = importer.finish()
    return blocks + tail, root


# ---- reader ----


def _pb_node(cid: CID, data: bytes) -> PBNode:
    """The dag-pb node of a block; a block that is not one is a UnixFS error naming it."""
    try:
        return PBNode.decode(data)
    except DagPbError as exc:
        raise UnixfsError(f"{cid} is not a dag-pb node: {exc}") from exc


def decode_node(cid: CID, data: bytes) -> tuple[PBNode, UnixfsData]:
    node = _pb_node(cid, data)
    if node.data is None:
        raise UnixfsError(f"{cid} is dag-pb without UnixFS data")
    return node, UnixfsData.decode(node.data)


def _file_node(cid: CID, data: bytes) -> tuple[PBNode, UnixfsData]:
    """A dag-pb file node whose declared sizes agree with each other."""
    node, unixfs = decode_node(cid, data)
    if unixfs.type not in (FILE, RAW_TYPE):
        raise UnixfsError(f"{cid} is not a file (UnixFS type {unixfs.type})")
    if len(unixfs.blocksizes) != len(node.links):
        raise UnixfsError(f"{cid} has {len(node.links)} links but {len(unixfs.blocksizes)} sizes")
    total = len(unixfs.data) + sum(unixfs.blocksizes)
    if unixfs.filesize is not None and unixfs.filesize != total:
        raise UnixfsError(
            f"{cid} declares a file of {unixfs.filesize} bytes but its data and blocksizes "
            f"add up to {total}"
        )
    return node, unixfs


def file_size(root: CID, get_block: GetBlock) -> int:
    """The size of a file's content, from its root block alone.

    The children are not read here, so this is what the root *declares*; :func:`read_file`
    checks every block it reads against it and fails rather than return fewer bytes.
    """
    data = get_block(root)
    if root.codec == RAW:
        return len(data)
    if root.codec != DAG_PB:
        raise UnixfsError(f"{root} is neither raw nor dag-pb")
    _, unixfs = _file_node(root, data)
    return len(unixfs.data) + sum(unixfs.blocksizes)


class _Span(NamedTuple):
    """A block still to read: the part ``[start, end)`` of its content, and what it holds."""

    cid: CID
    start: int
    end: int | None
    declared: int | None
    depth: int


def read_file(
    root: CID, get_block: GetBlock, offset: int = 0, length: int | None = None
) -> Iterator[bytes]:
    """Stream ``length`` bytes of a file from ``offset`` (to the end when ``length`` is None).

    Iterative, depth-first, touching only the blocks the range needs. Each child must hold
    exactly the size its parent declared for it, and no path may be deeper than
    ``MAX_DAG_DEPTH``: a lying or hostile DAG raises :class:`UnixfsError` naming the block,
    so a server that already promised a length can cut the response off instead of sending
    a short body as if it were complete.
    """
    end = None if length is None else offset + length
    for _, content, span in _file_blocks(root, get_block, offset, end):
        if content:
            yield content[span.start : span.end]


def file_range_blocks(
    root: CID, get_block: GetBlock, start: int, end: int | None
) -> Iterator[Block]:
    """The blocks of a file needed to verify its bytes ``[start, end)``, in CAR order."""
    for block, _, _ in _file_blocks(root, get_block, start, end, whole_root=True):
        yield block


def _file_blocks(
    root: CID, get_block: GetBlock, start: int, end: int | None, *, whole_root: bool = False
) -> Iterator[tuple[Block, bytes, _Span]]:
    """Each block a byte range of a file needs, with the file bytes it holds itself.

    The root is read even for an empty range when ``whole_root`` (a CAR of it must hold
    something to verify).
    """
    stack = [_Span(root, start, end, None, 0)]
    while stack:
        span = stack.pop()
        empty = span.end is not None and span.end <= span.start
        if empty and not (whole_root and span.cid == root and span.depth == 0):
            continue
        if span.depth > MAX_DAG_DEPTH:
            raise UnixfsError(f"{span.cid} lies deeper than {MAX_DAG_DEPTH} levels in {root}")
        data = get_block(span.cid)
        if span.cid.codec == RAW:
            _check_size(span, len(data), root)
            yield Block(span.cid, data), data, span
            continue
        if span.cid.codec != DAG_PB:
            raise UnixfsError(f"{span.cid} is neither raw nor dag-pb")
        node, unixfs = _file_node(span.cid, data)
        _check_size(span, len(unixfs.data) + sum(unixfs.blocksizes), root)
        yield Block(span.cid, data), unixfs.data, span
        if empty:
            continue
        children: list[_Span] = []
        position = len(unixfs.data)
        for link, size in zip(node.links, unixfs.blocksizes, strict=True):
            child_end = position + size
            if span.end is not None and position >= span.end:
                break
            if child_end > span.start:
                local_end = (
                    None if span.end is None or span.end >= child_end else span.end - position
                )
                children.append(
                    _Span(link.cid, max(0, span.start - position), local_end, size, span.depth + 1)
                )
            position = child_end
        stack.extend(reversed(children))


def _check_size(span: _Span, actual: int, root: CID) -> None:
    if span.declared is not None and actual != span.declared:
        raise UnixfsError(
            f"{span.cid} holds {actual} bytes but its parent in {root} declares {span.declared}"
        )


def assemble_file(
    root: CID, blocks: Iterator[Block], out: BinaryIO, progress: Callable[[int], object]
) -> int:
    """Write the file ``root`` from its blocks in DFS order (a CAR's), each checked as it comes.

    The streamed counterpart of :func:`read_file`, with the same rules (file nodes only,
    declared sizes kept, ``MAX_DAG_DEPTH``): each block was hashed against its own CID by
    whoever produced ``blocks``; this checks that it is the next block of *this* file's DAG,
    so the bytes written are exactly those ``root`` commits to, with bounded memory. A
    sender may send a repeated block (a run of zeros) only once, so leaves are remembered by
    their place in ``out`` (which must be readable) and inner nodes by their links, and a
    repeat is replayed from there. Returns the number of bytes written.
    """
    return _Assembly(root, out, progress).run(blocks)


class _Due(NamedTuple):
    cid: CID
    declared: int | None
    depth: int


class _Assembly:
    def __init__(self, root: CID, out: BinaryIO, progress: Callable[[int], object]) -> None:
        self.root = root
        self.out = out
        self.progress = progress
        self.written = 0
        self._leaves: dict[CID, tuple[int, int]] = {}
        self._inner: dict[CID, tuple[bytes, list[Link], list[int]]] = {}
        self._due: list[_Due] = [_Due(root, None, 0)]

    def run(self, blocks: Iterator[Block]) -> int:
        while self._due:
            due = self._due.pop()
            if due.depth > MAX_DAG_DEPTH:
                raise UnixfsError(
                    f"{due.cid} lies deeper than {MAX_DAG_DEPTH} levels in {self.root}"
                )
            if not self._replay(due):
                block = next(blocks, None)
                if block is None:
                    raise UnixfsError(f"the blocks end before block {due.cid} of {self.root}")
                if block.cid != due.cid:
                    raise UnixfsError(
                        f"block {block.cid} came where {due.cid} of {self.root} is due"
                    )
                self._take(due, block.data)
        if next(blocks, None) is not None:
            raise UnixfsError(f"there are blocks beyond the file {self.root}")
        return self.written

    def _replay(self, due: _Due) -> bool:
        if due.cid in self._leaves:
            offset, length = self._leaves[due.cid]
            self._check(due, length)
            self.out.seek(offset)
            data = self.out.read(length)
            self.out.seek(0, io.SEEK_END)
            self._write(data)
            return True
        if due.cid in self._inner:
            data, links, sizes = self._inner[due.cid]
            self._check(due, len(data) + sum(sizes))
            self._write(data)
            self._expect(links, sizes, due.depth)
            return True
        return False

    def _take(self, due: _Due, block: bytes) -> None:
        if due.cid.codec == RAW:
            self._check(due, len(block))
            self._leaves[due.cid] = (self.written, len(block))
            self._write(block)
            return
        if due.cid.codec != DAG_PB:
            raise UnixfsError(f"{due.cid} is neither raw nor dag-pb")
        node, unixfs = _file_node(due.cid, block)
        self._check(due, len(unixfs.data) + sum(unixfs.blocksizes))
        if node.links:
            self._inner[due.cid] = (unixfs.data, node.links, unixfs.blocksizes)
        else:
            self._leaves[due.cid] = (self.written, len(unixfs.data))
        self._write(unixfs.data)
        self._expect(node.links, unixfs.blocksizes, due.depth)

    def _expect(self, links: list[Link], sizes: list[int], depth: int) -> None:
        self._due.extend(
            _Due(link.cid, size, depth + 1)
            for link, size in zip(reversed(links), reversed(sizes), strict=True)
        )

    def _check(self, due: _Due, actual: int) -> None:
        if due.declared is not None and actual != due.declared:
            raise UnixfsError(
                f"{due.cid} holds {actual} bytes but its parent in {self.root} declares "
                f"{due.declared}"
            )

    def _write(self, data: bytes) -> None:
        self.out.write(data)
        self.written += len(data)
        self.progress(len(data))


def list_directory(root: CID, get_block: GetBlock) -> list[Link]:
    """The entries of a (non-sharded) UnixFS directory."""
    node, unixfs = decode_node(root, get_block(root))
    if unixfs.type != DIRECTORY:
        raise UnixfsError(f"{root} is not a directory (UnixFS type {unixfs.type})")
    return node.links


def walk_dag(root: CID, get_block: GetBlock, scope: str = "all") -> Iterator[Block]:
    """Blocks in CAR order (depth first, links in order, each block once).

    ``block``: the root only. ``entity``: the whole file, or a directory's own nodes (every
    level of a HAMT's shards included) without its entries' content. ``all``: everything
    reachable.
    """
    if scope not in ("block", "entity", "all"):
        raise UnixfsError(f"unknown dag-scope {scope!r}: expected block, entity or all")
    seen: set[CID] = set()
    stack: list[tuple[CID, int]] = [(root, 0)]
    while stack:
        cid, depth = stack.pop()
        if cid in seen:
            continue
        if depth > MAX_DAG_DEPTH:
            raise UnixfsError(f"{cid} lies deeper than {MAX_DAG_DEPTH} levels under {root}")
        seen.add(cid)
        data = get_block(cid)
        yield Block(cid, data)
        if scope == "block" or cid.codec != DAG_PB:
            continue
        node = _pb_node(cid, data)
        links = node.links
        if scope == "entity" and node.data is not None:
            links = _entity_links(cid, node)
        stack.extend((link.cid, depth + 1) for link in reversed(links))


def _entity_links(cid: CID, node: PBNode) -> list[Link]:
    """The links an entity walk follows: all of a file's, a HAMT's shard links, no entries."""
    assert node.data is not None
    unixfs = UnixfsData.decode(node.data)
    if unixfs.type == DIRECTORY:
        return []
    if unixfs.type == HAMT_SHARD:
        fanout = unixfs.fanout or 0
        if fanout < 2 or fanout & (fanout - 1):
            raise UnixfsError(f"{cid} is a HAMT shard with an invalid fanout {fanout}")
        width = len(f"{fanout - 1:X}")
        return [link for link in node.links if len(link.name) == width]
    return node.links
