"""UnixFS over dag-pb: the importer that gives a file its IPFS CID, the reader, the DAG walk.

The importer reproduces ``ipfs add``: fixed-size chunks, a balanced tree with at most
``max_links`` links per node, raw leaves with CIDv1. It is incremental (``feed`` and
``finish``) so a server can hash an upload while it streams in, holding one chunk plus one
pending link list per tree level.

There is one reader, :func:`read_nodes`, over a source of nodes: :func:`read_file` gives it a
block store (random access: a byte range touches only the blocks it needs, UnixFS
``blocksizes`` saying where each child starts), :func:`file_range_blocks` the same store
while keeping the blocks it visits (a CAR of a byte range), :func:`write_file` blocks taken
in a CAR's order (the SDK's verified download, :func:`assemble_file` from one file's CAR)
and :func:`read_car_range` a CAR of a range (the SDK's verified ``cat``). All therefore
keep the same rules: file nodes only, every child the size its parent declares, no path
deeper than :data:`MAX_DAG_DEPTH`, no more blocks visited than :func:`visit_budget` allows
and no more bytes of blocks read than :func:`read_budget` allows.
Nothing here recurses, so a hostile DAG meets a named limit, never Python's stack (which
py_ecc lets grow to 100,000 frames, past what the C stack holds).
"""

from __future__ import annotations

import io
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import BinaryIO, NamedTuple

from robocloud.cid import CID, DAG_CBOR, DAG_JSON, DAG_PB, RAW, Block
from robocloud.dagcbor import DagCborError
from robocloud.dagcbor import links as dag_cbor_links
from robocloud.dagjson import DagJsonError
from robocloud.dagjson import links as dag_json_links
from robocloud.dagpb import DagPbError, Link, PBNode, fields, len_field, read_uint, uint_field
from robocloud.errors import FormatError

DEFAULT_CHUNK_SIZE = 262_144
DEFAULT_MAX_LINKS = 174
MAX_CHUNK_SIZE = 2 * 1024 * 1024
MAX_DAG_DEPTH = 1024
"""Deepest level (the root is level 0) a read or walk follows; a deeper DAG is refused.

A file's tree is shallow whatever made it: a balanced tree of ``max_links`` links is
log_max_links(chunks) levels deep (3 for 1 TiB in 256 KiB chunks under 174 links, 2 under
the 1,024 of ``unixfs-v1-2025``; 64 at worst, 2^64 one-byte chunks under 2 links), and
kubo's trickle layout (``ipfs add --trickle``) multiplies its leaves by 5 per level (174
leaves, then 4 repeats of each depth), so 1 TiB in 256 KiB chunks is 8 levels deep and 2^64
one-byte chunks 26. Directories nest as their paths do, one level each (plus a HAMT's
shards, 2 to 4 levels for a million entries): macOS stops a path at 1,024 bytes (512
one-letter levels) and Linux at 4,096. 1,024 levels hold any file below any directory macOS
can name, with room to spare, while a chain built to be deep (the 30,000 levels of a 2.6 MB
CAR) is refused when it reaches level 1,025."""
PROFILES: dict[str, tuple[int, int, bool, int, bool]] = {
    # name: (cid_version, chunk size, raw leaves, max links, shard by exact block size)
    "unixfs-v0-2015": (0, DEFAULT_CHUNK_SIZE, False, DEFAULT_MAX_LINKS, False),
    "unixfs-v1-2025": (1, 1_048_576, True, 1024, True),
}

# UnixFS Data.Type
RAW_TYPE, DIRECTORY, FILE, METADATA, SYMLINK, HAMT_SHARD = range(6)
MURMUR3_X64_64 = 0x22
"""The multihash code of the hash HAMT shards bucket names by (their ``hashType``)."""
MIN_HAMT_FANOUT, MAX_HAMT_FANOUT = 8, 1024
"""The fanouts boxo loads: its bitfield is whole bytes (go-bitfield refuses a size that is not
a multiple of 8) and its ``maximumHamtWidth`` is 1,024; between them, any power of two."""


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
    """The UnixFS ``Data`` message a dag-pb node carries (fields 1 to 6; mode and mtime,
    which nothing here needs, are skipped). ``hash_type`` and ``fanout`` belong to HAMT
    shards."""

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
        except DagPbError as exc:
            raise UnixfsError(f"invalid UnixFS data: {exc}") from exc

    @classmethod
    def _decode(cls, raw: bytes) -> UnixfsData:
        node = cls(type=-1)
        for number, value in fields(raw):
            if number == 2:
                node.data = _bytes_field(value, "Data")
            elif number == 4 and isinstance(value, bytes):  # packed encoding
                pos = 0
                while pos < len(value):
                    size, pos = read_uint(value, pos, len(value))
                    node.blocksizes.append(size)
            elif number in _UINT_FIELDS:
                number_value = _uint_field(value, _UINT_FIELDS[number])
                if number == 1:
                    node.type = number_value
                elif number == 3:
                    node.filesize = number_value
                elif number == 4:
                    node.blocksizes.append(number_value)
                elif number == 5:
                    node.hash_type = number_value
                elif number == 6:
                    node.fanout = number_value
        if not RAW_TYPE <= node.type <= HAMT_SHARD:
            raise UnixfsError(
                "UnixFS data without a type" if node.type < 0 else f"unknown type {node.type}"
            )
        return node


_UINT_FIELDS = {1: "Type", 3: "filesize", 4: "blocksizes", 5: "hashType", 6: "fanout"}


def _uint_field(value: int | bytes, name: str) -> int:
    if not isinstance(value, int):
        raise UnixfsError(f"UnixFS {name} must be a varint, not bytes")
    return value


def _bytes_field(value: int | bytes, name: str) -> bytes:
    if not isinstance(value, bytes):
        raise UnixfsError(f"UnixFS {name} must be bytes, not a varint")
    return value


def hamt_prefix_width(cid: CID, unixfs: UnixfsData) -> int:
    """How many hex digits name a bucket of the HAMT shard ``cid``: a link to a sub-shard is
    named exactly that, a link to an entry that plus the entry's name.

    Only shards boxo reads are accepted (murmur3 x64 64 names, a fanout ``hamt_fanout_ok``
    allows), so walking and resolving refuse the same shards kubo would.
    """
    fanout = unixfs.fanout or 0
    if unixfs.hash_type != MURMUR3_X64_64 or not hamt_fanout_ok(fanout):
        raise UnixfsError(
            f"{cid} is a HAMT shard of an unsupported kind (hashType {unixfs.hash_type}, "
            f"fanout {unixfs.fanout})"
        )
    return len(f"{fanout - 1:X}")


def hamt_fanout_ok(fanout: int) -> bool:
    """Whether boxo can load (and so kubo can write) a HAMT shard of ``fanout`` buckets: a
    power of two from ``MIN_HAMT_FANOUT`` to ``MAX_HAMT_FANOUT``; each level of the HAMT
    takes log2(fanout) bits of a name's hash."""
    return MIN_HAMT_FANOUT <= fanout <= MAX_HAMT_FANOUT and fanout & (fanout - 1) == 0


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


class FileNode(NamedTuple):
    """One block of a file as the reader sees it, whatever its codec.

    ``data`` is the content the block holds itself (all of a raw leaf), ``links`` and
    ``sizes`` its children and the content size it declares for each, ``size`` the content
    it stands for (its data plus its children's declared sizes), ``read`` the bytes it took
    to get it (its whole block, whatever the block carries beside the content).
    """

    data: bytes
    links: Sequence[CID]
    sizes: Sequence[int]
    size: int
    read: int


NodeSource = Callable[[CID], FileNode]
"""Where the reader gets the next node it needs: a block store, or a CAR's stream of blocks."""


def _pb_node(cid: CID, data: bytes) -> PBNode:
    """The dag-pb node of a block; a block that is not one is a UnixFS error naming it."""
    try:
        return PBNode.decode(data)
    except DagPbError as exc:
        raise UnixfsError(f"{cid} is not a dag-pb node: {exc}") from exc


def _unixfs_data(cid: CID, node: PBNode) -> UnixfsData:
    if node.data is None:
        raise UnixfsError(f"{cid} is dag-pb without UnixFS data")
    try:
        return UnixfsData.decode(node.data)
    except UnixfsError as exc:
        raise UnixfsError(f"{cid}: {exc}") from exc


def decode_node(cid: CID, data: bytes) -> tuple[PBNode, UnixfsData]:
    """A dag-pb block and the UnixFS data it carries; errors name the block."""
    node = _pb_node(cid, data)
    return node, _unixfs_data(cid, node)


def file_node(cid: CID, block: bytes) -> FileNode:
    """The file node a block is, its declared sizes agreeing with each other.

    A dag-pb node must be a UnixFS file (or raw) node with one blocksize per link and, when
    it states a filesize, exactly its data plus its blocksizes.
    """
    if cid.codec == RAW:
        return FileNode(block, (), (), len(block), len(block))
    if cid.codec != DAG_PB:
        raise UnixfsError(f"{cid} is neither raw nor dag-pb")
    node, unixfs = decode_node(cid, block)
    if unixfs.type not in (FILE, RAW_TYPE):
        raise UnixfsError(f"{cid} is not a file (UnixFS type {unixfs.type})")
    if len(unixfs.blocksizes) != len(node.links):
        raise UnixfsError(f"{cid} has {len(node.links)} links but {len(unixfs.blocksizes)} sizes")
    size = len(unixfs.data) + sum(unixfs.blocksizes)
    if unixfs.filesize is not None and unixfs.filesize != size:
        raise UnixfsError(
            f"{cid} declares a file of {unixfs.filesize} bytes but its data and blocksizes "
            f"add up to {size}"
        )
    return FileNode(
        unixfs.data, [link.cid for link in node.links], unixfs.blocksizes, size, len(block)
    )


def file_size(root: CID, get_block: GetBlock) -> int:
    """The size of a file's content, from its root block alone.

    The children are not read here, so this is what the root *declares*; :func:`read_file`
    checks every block it reads against it and fails rather than return fewer bytes.
    """
    return file_node(root, get_block(root)).size


class _Span(NamedTuple):
    """A block still to read: the part ``[start, end)`` of its content (``end`` None: all of
    it from ``start``), the size its parent declares for it, and where its content begins in
    the file (for messages)."""

    cid: CID
    start: int
    end: int | None
    declared: int | None
    at: int


def read_file(
    root: CID, get_block: GetBlock, offset: int = 0, length: int | None = None
) -> Iterator[bytes]:
    """Stream ``length`` bytes of a file from ``offset`` (to the end when ``length`` is None).

    Random access over a block store: only the blocks the range needs are fetched.
    """
    return read_nodes(root, lambda cid: file_node(cid, get_block(cid)), offset, length)


def file_range_blocks(
    root: CID, get_block: GetBlock, start: int, end: int | None
) -> Iterator[Block]:
    """The blocks of a file needed to verify its bytes ``[start, end)``, in CAR order.

    Exactly the blocks :func:`read_nodes` visits to read those bytes, so a CAR of a range
    keeps the reader's rules and bounds (declared sizes, depth, visit budget). An empty
    range still gives the root, checked as a file node: a CAR must hold something to verify.
    """
    visited: list[Block] = []

    def node_of(cid: CID) -> FileNode:
        block = get_block(cid)
        visited.append(Block(cid, block))
        return file_node(cid, block)

    if end is not None and end <= start:
        node_of(root)
    else:
        for _ in read_nodes(root, node_of, start, None if end is None else end - start):
            yield from visited
            visited.clear()
    yield from visited


def read_nodes(
    root: CID, node_of: NodeSource, offset: int = 0, length: int | None = None
) -> Iterator[bytes]:
    """The one UnixFS file reader: ``length`` bytes from ``offset``, in file order.

    Depth first and iterative: one frame per level, each a lazy walk over its node's
    children, so memory grows with the depth and never with the fan-out. A child is visited
    only when its part of the file meets the range (a whole read visits every one, empty
    ones too, as a CAR carries them). Each child must stand for exactly the size its parent
    declared for it, no path may be deeper than ``MAX_DAG_DEPTH``, the blocks visited may
    not outnumber what :func:`visit_budget` allows for the bytes yielded, nor their bytes
    (``FileNode.read``) pass what :func:`read_budget` allows: a lying or hostile DAG raises
    :class:`UnixfsError` naming the block, so a server that already promised a length cuts
    the response off instead of sending a short body as if it were complete, and no DAG
    makes a read work long for little (a few blocks linked thousands of times over, each
    standing for nothing, behind a long chain, or carrying megabytes beside its one byte).
    """
    if offset < 0 or (length is not None and length < 0):
        raise UnixfsError(f"no bytes at offset {offset}, length {length}")
    end = None if length is None else offset + length
    if end is not None and end == offset:
        return
    frames: list[Iterator[_Span]] = [iter((_Span(root, offset, end, None, 0),))]
    visited = yielded = read = 0
    while frames:
        span = next(frames[-1], None)
        if span is None:
            frames.pop()
            continue
        if len(frames) > MAX_DAG_DEPTH + 1:
            raise UnixfsError(
                f"{span.cid} (byte {span.at} of {root}) lies deeper than {MAX_DAG_DEPTH} "
                "levels, the limit"
            )
        visited += 1
        if visited > visit_budget(yielded):
            raise UnixfsError(
                f"{root} takes more than {visited - 1} blocks for its first {yielded} bytes "
                f"(the limit; at {span.cid}, byte {span.at}): its blocks repeat to no end"
            )
        node = node_of(span.cid)
        piece = node.data[span.start : span.end] if span.start < len(node.data) else b""
        read += node.read
        if read > read_budget(yielded + len(piece)):
            raise UnixfsError(
                f"{root} takes more than {read_budget(yielded + len(piece))} bytes of blocks "
                f"for its first {yielded + len(piece)} bytes (the limit; at {span.cid}, byte "
                f"{span.at}): its blocks hold far more than the file"
            )
        if span.declared is not None and node.size != span.declared:
            raise UnixfsError(
                f"{span.cid} holds {node.size} bytes but its parent in {root} declares "
                f"{span.declared} (the block at byte {span.at} of the file)"
            )
        if piece:
            yielded += len(piece)
            yield piece
        if node.links:
            frames.append(_children(node, span))


def visit_budget(yielded: int) -> int:
    """How many blocks a read may have visited once it has yielded ``yielded`` bytes.

    Two per byte: an importer's tree has at most one inner node per leaf plus a few on its
    right spine (3,072 one-byte chunks under 2 links make 3,072 inner nodes), and a leaf
    holds at least one byte (a chunk). Plus two root-to-leaf paths, the ones a range starts
    and ends on. Reading any imported file spends at most half of it; a DAG that repeats a
    subtree standing for nothing, or a byte behind a long chain, runs out of it.
    """
    return 2 * yielded + 2 * (MAX_DAG_DEPTH + 1)


READ_FACTOR = 256
"""Bytes of blocks a read may take per byte it yields, beyond :data:`READ_ALLOWANCE`.

A file's blocks hold its content plus their protobuf: a few bytes per dag-pb leaf and about
50 per link (a 36-byte CID, its Tsize, the child's blocksize). Files of kubo's chunks read at
1.0x; the worst any importer makes, one-byte chunks under 2 links, hold a leaf and a
two-link node per byte: 100x to 108x measured (CIDv0 or v1, raw or dag-pb leaves), under 200x
with 64-byte hashes. 256 reads every such file, while a block carrying megabytes beside the
one byte it stands for (an unknown UnixFS field) is refused after a few visits: a read
hashes at most 256 bytes per byte sent (a fraction of a microsecond, less than the Python
work of one of the two block visits per byte :func:`visit_budget` already allows)."""

READ_ALLOWANCE = 4 * MAX_CHUNK_SIZE
"""Bytes of blocks (8 MiB) any read may take beyond ``READ_FACTOR`` per byte: what the two
root-to-leaf paths a range starts and ends on hold outside it. Each ends in a leaf the range
may cut (at most ``MAX_CHUNK_SIZE``, 2 MiB; kubo's chunks stop at 1 MiB) and passes inner
nodes whose other links lead outside the range: 2 MiB, two levels of nodes as large as kubo
makes a block (1 MiB) or the 1,025 levels of ``MAX_DAG_DEPTH`` at 2 KiB, where an importer's
file is at most a few levels of 10 to 60 KiB (174 or 1,024 links)."""


def read_budget(yielded: int) -> int:
    """How many bytes of blocks a read may have taken once it has yielded ``yielded`` bytes
    (counting those of the block just read): ``READ_FACTOR`` per byte plus
    ``READ_ALLOWANCE``. The bytes of a block visited twice count twice, as they are read and
    hashed twice; the check comes after a block is fetched, so a refused read has taken at
    most one block more than its budget."""
    return READ_FACTOR * yielded + READ_ALLOWANCE


def _children(node: FileNode, span: _Span) -> Iterator[_Span]:
    """The spans of ``node``'s children that meet ``span``'s range, in order, as needed."""
    start, end = span.start, span.end
    position = len(node.data)
    for cid, size in zip(node.links, node.sizes, strict=True):
        if end is not None and position >= end:
            return
        child_end = position + size
        if child_end > start or (size == 0 and position >= start):
            local_end = None if end is None or end >= child_end else end - position
            yield _Span(cid, max(0, start - position), local_end, size, span.at + position)
        position = child_end


MAX_FILE_NODES = 1 << 20
"""Distinct blocks a file read from a CAR may have (about 230 bytes of bookkeeping each):
256 GiB at kubo's 256 KiB chunks, 16 MiB at 16-byte ones."""


def assemble_file(
    root: CID,
    blocks: Iterator[Block],
    out: BinaryIO,
    progress: Callable[[int], object],
    *,
    max_nodes: int = MAX_FILE_NODES,
) -> int:
    """Write the file ``root`` from its blocks in DFS order (a CAR's), each checked as it comes.

    :func:`write_file` over :func:`blocks_due`: each block was hashed against its own CID by
    whoever produced ``blocks``, and must be the next block of *this* file's DAG, so the
    bytes written are exactly those ``root`` commits to; no block may follow the file.
    Returns the bytes written.
    """
    written = write_file(root, blocks_due(root, blocks), out, progress, max_nodes=max_nodes)
    if next(blocks, None) is not None:
        raise UnixfsError(f"there are blocks beyond the file {root}")
    return written


def write_file(
    root: CID,
    take: GetBlock,
    out: BinaryIO,
    progress: Callable[[int], object],
    *,
    max_nodes: int = MAX_FILE_NODES,
) -> int:
    """Write the file ``root`` with bounded memory, asking ``take`` for each distinct block
    once, in the order a CAR carries them (depth first).

    :func:`read_nodes`, so the rules are those of :func:`read_file`. A CAR carries a
    repeated block (a run of zeros) only once, so the content each node holds is remembered
    by its place in ``out`` (which must be readable) and an inner node by its block, and a
    repeat is replayed from there rather than asked for. A file of more than ``max_nodes``
    distinct blocks is refused. Returns the bytes written.
    """
    source = _CarOrder(root, take, out, max_nodes)
    for piece in read_nodes(root, source.node):
        out.write(piece)
        source.written += len(piece)
        progress(len(piece))
    return source.written


def blocks_due(root: CID, blocks: Iterator[Block]) -> GetBlock:
    """``blocks`` as a source that must give each block in the order it is asked for: the
    stream a CAR of ``root`` is, read by a walk that knows which block comes next."""

    def take(cid: CID) -> bytes:
        block = next(blocks, None)
        if block is None:
            raise UnixfsError(f"the blocks end before block {cid} of {root}")
        if block.cid != cid:
            raise UnixfsError(f"block {block.cid} came where {cid} of {root} is due")
        return bytes(block.data)

    return take


def read_car_range(
    root: CID,
    blocks: Iterator[Block],
    offset: int,
    length: int | None,
    *,
    max_block_bytes: int,
) -> Iterator[bytes]:
    """``length`` bytes of the file ``root`` from ``offset``, from a CAR of that range.

    The CAR a trustless gateway answers to ``entity-bytes`` holds the blocks :func:`read_nodes`
    visits for the range, in that order, a repeated one once; so each unseen block asked for
    must be the next one, and a repeat comes from what was kept. A range's edge leaves are
    only partly in the answer, which is why blocks are kept whole here rather than replayed
    from the output as :func:`write_file` does; their bytes together may not pass
    ``max_block_bytes``. Each block was hashed against its own CID by whoever produced
    ``blocks``; the reader's rules make them this file's, and no block may follow the range.
    """
    kept: dict[CID, bytes] = {}
    kept_bytes = 0
    take = blocks_due(root, blocks)

    def node_of(cid: CID) -> FileNode:
        nonlocal kept_bytes
        data = kept.get(cid)
        if data is None:
            data = take(cid)
            kept_bytes += len(data)
            if kept_bytes > max_block_bytes:
                raise UnixfsError(
                    f"the range of {root} takes more than {max_block_bytes} bytes of blocks"
                )
            kept[cid] = data
        return file_node(cid, data)

    yield from read_nodes(root, node_of, offset, length)
    if next(blocks, None) is not None:
        raise UnixfsError(f"there are blocks beyond the range of {root}")


class _Replay(NamedTuple):
    """An inner node already received: where its own content lies in the output, and its
    block, decoded again when it repeats (its links as CID objects would be 200 bytes each)."""

    at: int
    length: int
    block: bytes


class _CarOrder:
    """The nodes of one file from its blocks in the order a CAR of it carries them.

    The reader asks for nodes in the order it writes the file, so each unseen node is taken
    as the next block, and ``written`` (kept by the caller) is where that node's own
    content goes. A node asked for again is not in the CAR again: it is rebuilt from
    ``out`` and what is kept for it: an inner node's block, decoded again, and for a leaf one
    integer keyed by its binary CID. What is kept grows with the file's distinct nodes, so
    their number is bounded: a 6 MB file chunked by 16 bytes is 400,000 of them.
    """

    def __init__(
        self, root: CID, take: GetBlock, out: BinaryIO, max_nodes: int = MAX_FILE_NODES
    ) -> None:
        self.root = root
        self.take = take
        self.out = out
        self.written = 0
        self.max_nodes = max_nodes
        self._inner: dict[CID, _Replay] = {}
        self._leaves: dict[bytes, int] = {}
        """A leaf's place in ``out``: ``at << 32 | length``."""

    def node(self, cid: CID) -> FileNode:
        inner = self._inner.get(cid)
        if inner is not None:
            node = file_node(cid, inner.block)
            return node._replace(data=self._reread(inner.at, inner.length))
        leaf = self._leaves.get(cid.binary)
        if leaf is not None:
            data = self._reread(leaf >> 32, leaf & 0xFFFFFFFF)
            return FileNode(data, (), (), len(data), len(data))
        return self._next_node(cid)

    def _next_node(self, cid: CID) -> FileNode:
        data = self.take(cid)
        if len(self._inner) + len(self._leaves) >= self.max_nodes:
            raise UnixfsError(
                f"{self.root} has more than {self.max_nodes} distinct blocks, more than a "
                "download keeps track of (a file chunked into tiny pieces)"
            )
        node = file_node(cid, data)
        if node.links:
            self._inner[cid] = _Replay(self.written, len(node.data), data)
        else:
            self._leaves[cid.binary] = self.written << 32 | len(node.data)
        return node

    def _reread(self, at: int, length: int) -> bytes:
        if not length:
            return b""
        self.out.seek(at)
        data = self.out.read(length)
        self.out.seek(0, io.SEEK_END)
        if len(data) != length:
            raise UnixfsError(f"the output of {self.root} lost {length - len(data)} bytes")
        return data


# ---- directories and DAG walks ----


def list_directory(root: CID, get_block: GetBlock) -> list[Link]:
    """The entries of a (non-sharded) UnixFS directory."""
    node, unixfs = decode_node(root, get_block(root))
    if unixfs.type != DIRECTORY:
        raise UnixfsError(f"{root} is not a directory (UnixFS type {unixfs.type})")
    return node.links


def walk_dag(
    root: CID,
    get_block: GetBlock,
    scope: str = "all",
    seen: set[CID] | None = None,
    on_links: Callable[[CID, list[CID]], None] | None = None,
) -> Iterator[Block]:
    """Blocks in CAR order (depth first, links in order, each block once).

    ``block``: the root only. ``entity``: the whole file, or a directory's own nodes (every
    level of a HAMT's shards, whose links to sub-shards are named by their bucket alone)
    without its entries' content; a dag-cbor or dag-json block alone, as the trustless
    gateway specification has it for data that is not UnixFS. ``all``: everything reachable,
    through dag-pb, dag-cbor and dag-json links alike, as kubo's recursive pin and
    ``dag export`` go. Iterative with one frame per level, bounded by ``MAX_DAG_DEPTH`` as
    the reader is.

    ``seen`` holds blocks an earlier walk went through to its end, skipped with everything
    under them: shared by the walks of several roots, it reads a common sub-DAG once. A walk
    cut short (a block missing or malformed, the caller gone) takes back the blocks it had
    not finished, the path down to where it stopped, so ``seen`` stays true for the next.

    ``on_links`` (scope ``all``) hears each block's links once the walk has decoded them, so
    that a caller needing them (the cas, sizing a DAG) does not decode every block again.
    """
    if scope not in ("block", "entity", "all"):
        raise UnixfsError(f"unknown dag-scope {scope!r}: expected block, entity or all")
    seen = set() if seen is None else seen
    frames: list[Iterator[CID]] = [iter((root,))]
    path: list[CID] = []  # the block whose links each frame but the first walks
    cid: CID | None = None
    try:
        while frames:
            cid = next(frames[-1], None)
            if cid is None:
                frames.pop()
                if path:
                    path.pop()
                continue
            if cid in seen:
                continue
            if len(frames) > MAX_DAG_DEPTH + 1:
                raise UnixfsError(f"{cid} lies deeper than {MAX_DAG_DEPTH} levels under {root}")
            seen.add(cid)
            data = get_block(cid)
            yield Block(cid, data)
            if scope == "block":
                continue
            if cid.codec in (DAG_CBOR, DAG_JSON):
                if scope == "entity":
                    continue
                children = links_of(cid, data)
            elif cid.codec == DAG_PB:
                node = _pb_node(cid, data)
                children = [link.cid for link in node.links]
                if scope == "entity" and node.data is not None:
                    unixfs = _unixfs_data(cid, node)
                    if unixfs.type == DIRECTORY:
                        children = []
                    elif unixfs.type == HAMT_SHARD:
                        width = hamt_prefix_width(cid, unixfs)
                        children = [link.cid for link in node.links if len(link.name) == width]
            else:
                children = []
            if on_links is not None and scope == "all":
                on_links(cid, children)
            if children:
                frames.append(iter(children))
                path.append(cid)
    except BaseException:
        seen.difference_update(path)
        if cid is not None:
            seen.discard(cid)
        raise


LINKING_CODECS = frozenset({DAG_PB, DAG_CBOR, DAG_JSON})
"""The codecs whose blocks link to others; a block of any other codec is a leaf."""


def links_of(cid: CID, data: bytes) -> list[CID]:
    """What the block ``data`` of ``cid`` links to, in order; ``UnixfsError`` naming the
    block when it does not decode as its codec. Empty for codecs outside
    ``LINKING_CODECS``."""
    if cid.codec == DAG_PB:
        return [link.cid for link in _pb_node(cid, data).links]
    try:
        if cid.codec == DAG_CBOR:
            return dag_cbor_links(data)
        if cid.codec == DAG_JSON:
            return dag_json_links(data)
    except (DagCborError, DagJsonError) as exc:
        codec = "dag-cbor" if cid.codec == DAG_CBOR else "dag-json"
        raise UnixfsError(f"{cid} is not a {codec} block: {exc}") from exc
    return []
