"""Reading ROS bags: ROS 1 ``.bag``, ROS 2 directories (sqlite3 or MCAP, split or not) and bare
``.mcap`` / ``.db3`` files, through rosbags.

Why not rosbags' ``AnyReader`` as it is: it parses every connection's definition into one
typestore while opening, so a single unparsable definition (the service-event schemas of
ROS 2 Iron bags) makes the whole file unreadable; it matches a ROS 2 directory's metadata to
its storage files by QoS, so bags whose ``metadata.yaml`` spells QoS differently yield nothing;
and it does not check MCAP CRCs, so a corrupt compressed chunk silently loses messages. Here
each distinct definition gets its own typestore (a bad one disables only its topics), storage
connections are matched on topic and type, chunk CRCs are checked, and every failure names the
file and, where the format has one, the byte offset.

Types come from the definitions the bag carries (ROS 1 always, ROS 2 since Iron or when written
by rosbags). A connection without one falls back to rosbags' bundled typestore of the bag's ROS
generation; a type found in neither cannot be decoded and is reported as such.
"""

from __future__ import annotations

import bz2
import heapq
import re
from collections import Counter
from collections.abc import Callable, Collection, Iterator, Mapping
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from enum import Enum
from functools import cache, partial
from itertools import pairwise
from operator import itemgetter
from pathlib import Path
from typing import Any, Literal, Self

import lz4.frame  # type: ignore[import-untyped]
from backports import zstd
from mcap.records import Chunk, Message, MessageIndex, Statistics
from mcap.stream_reader import CRCValidationError, StreamReader, breakup_chunk
from rosbags.interfaces import Connection, MessageDefinitionFormat, Nodetype
from rosbags.rosbag1 import Reader as Rosbag1Reader
from rosbags.rosbag1 import ReaderError as Rosbag1ReaderError
from rosbags.rosbag1 import reader as rosbag1_reader
from rosbags.rosbag2 import Reader as Rosbag2Reader
from rosbags.rosbag2 import ReaderError as Rosbag2ReaderError
from rosbags.rosbag2 import storage_mcap as rosbag2_mcap
from rosbags.typesys import Stores, TypesysError, get_types_from_idl, get_types_from_msg
from rosbags.typesys import get_typestore as bundled_typestore
from rosbags.typesys.store import Typestore

ROS1_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
IDL_SEPARATOR = "=" * 80 + "\n"
MAX_CHUNK_BYTES = 64 * 1024**2
"""The most one chunk (MCAP or ROS 1) may hold decompressed. Every reader here decompresses a
chunk whole, so a chunk is what a bag can make the service hold at once, and compression
lets a few bytes claim anything: 32 KiB of zstd declaring 1 GiB of zeros took 2.1 GiB. Real
writers stay far below: rosbag2's MCAP plugin closes a chunk at 1 MiB (the largest in the
recordings under shared/data is 1.02 MiB), rosbag and rosbags' ROS 1 writers at 768 KiB."""


FALLBACK_STORES = (Stores.ROS1_NOETIC, Stores.ROS2_HUMBLE)
"""rosbags' typestores for the types of a ROS 1 and of a ROS 2 bag that carries no
definition of its own."""

MAX_UNROLLED = 1024
"""Elements of fixed-size arrays of strings or of messages that one bag's definitions may
hold in all. rosbags generates each type's (de)serializers with a line of Python per such
element (a fixed array of numbers is one line whatever its length), at open: ``string[100000]
s``, 17 bytes of a definition, took 129 s and 3.9 GiB to compile, so a bag of no message
held the ingest thread and took the service's memory. No type in rosbags' typestores has
one; a real definition's few (``Point[4] corners``) cost about a millisecond each."""


MAX_DEFINITION_BYTES = 4 * 1024**2
"""Bytes of definition text one bag's distinct definitions may hold in all. rosbags parses
about a megabyte a second (pure Python), on the ingest thread: nothing bounded a
definition, so one of 64 MiB in a bag of no message would hold the thread for a minute.
The largest in the recordings under shared/data is 5.8 kB (``ParameterEvent`` with what it
holds); a bag of a hundred topics of distinct types holds a few hundred kB."""

MAX_TYPE_DEPTH = 64
"""Message types held inside one another, from a topic's type. rosbags builds a type's
(de)serializers by recursion into the types its fields hold: a definition of 600 types
chained (65 kB), or of one type holding itself (ROS has no recursive messages), raised
RecursionError, which failed the whole bag's job. Real definitions nest a handful
(``nav_msgs/msg/Odometry``: 4)."""


MAX_NAME = 1024
"""Characters of a topic's or a message type's name. The job's report names each topic and
type, and is written again at each step of the job: a type name of a megabyte made a
report of a megabyte, and a bag may hold 4,096 of them. ROS names are far shorter (records
hold a topic of at most 256 characters; a longer one is skipped alone)."""

MAX_TOPICS = 4096
"""Topics (a topic and its type) one bag may hold. Each costs the ingest thread a typestore
entry and a draft or a plan, and the job's report its line, saved with the job at every step:
40,000 empty IMU connections (67 MB of bag) took 1.8 s to open and draft and made a report of
21 MB, and a bag may hold 16 GiB of them. Real robots record tens to hundreds of topics."""


class BagFormat(Enum):
    ROS1 = "ros1"
    ROS2_DIRECTORY = "ros2"
    MCAP = "mcap"
    SQLITE3 = "db3"


class BagError(Exception):
    """A bag cannot be read; ``path`` names the file, ``offset`` the byte where known.

    Its text names the file as this node has it, for logs. The robot that sent the bag is
    told :meth:`shown` instead: a file of a ROS 2 bag directory by its path there, and the
    bag itself as "the bag", since the names a node gives what it receives (``upload``,
    ``bag.mcap``) were never the robot's (a failed upload said ``bag.bag: ...`` of the
    robot's ``run.bag``).
    """

    def __init__(self, message: str, *, path: Path, offset: int | None = None) -> None:
        super().__init__(_located(path.name, offset, message))
        self.reason = message
        self.path = path
        self.offset = offset

    def file_in(self, bag: Path) -> str | None:
        """The damaged file's path within ``bag``; None when it is ``bag`` itself."""
        if self.path == bag or not self.path.is_relative_to(bag):
            return None
        return self.path.relative_to(bag).as_posix()

    def shown(self, bag: Path) -> str:
        """What the robot that sent ``bag`` is told."""
        return _located(self.file_in(bag) or "the bag", self.offset, self.reason)


def _located(where: str, offset: int | None, reason: str) -> str:
    return f"{where}: {reason}" if offset is None else f"{where} at byte {offset}: {reason}"


class BagUnreadable(BagError):
    """Not a bag this reader knows: unknown magic, missing metadata, unsupported storage."""


class BagCorrupt(BagError):
    """A bag that is truncated or whose bytes are damaged."""


class ChunkTooLarge(ValueError):
    """A chunk that decompresses (or says it does) to more than it may: see
    :data:`MAX_CHUNK_BYTES`. A ValueError, as rosbags' own failures to read a chunk are."""


_DECOMPRESSORS: dict[str, Callable[[], Any]] = {
    "zstd": zstd.ZstdDecompressor,
    "lz4": lz4.frame.LZ4FrameDecompressor,
    "bz2": bz2.BZ2Decompressor,
}
"""Incremental decompressors: unlike a whole-buffer ``decompress``, each stops at a length."""


def inflate(compression: str, data: bytes, limit: int = MAX_CHUNK_BYTES) -> bytes:
    """``data`` decompressed, refused as soon as it passes ``limit`` bytes, so a bomb costs
    ``limit`` bytes and no more. One whole frame (stream) only: writers give a chunk one, and
    whatever followed it would otherwise decompress unbounded in rosbags after this check."""
    if not compression:
        inflated = data
    else:
        decompressor = _DECOMPRESSORS[compression]()
        inflated = decompressor.decompress(data, max_length=limit + 1)
        if len(inflated) <= limit and (not decompressor.eof or decompressor.unused_data):
            raise ValueError(f"the chunk's {compression} data is not one whole frame")
    if len(inflated) > limit:
        raise ChunkTooLarge(
            f"chunk decompresses to more than {limit} bytes ({compression or 'uncompressed'})"
        )
    return inflated


def inflate_declared(compression: str, data: bytes, declared: int) -> bytes:
    """A chunk that declares its size (MCAP's ``uncompressed_size``) decompressed: refused
    before any decompression when it declares more than :data:`MAX_CHUNK_BYTES`, and as soon
    as it passes what it declares."""
    if declared > MAX_CHUNK_BYTES:
        raise ChunkTooLarge(
            f"chunk declares {declared} bytes decompressed, more than the {MAX_CHUNK_BYTES} "
            "a chunk may hold"
        )
    return inflate(compression, data, declared)


def _bound_rosbags() -> None:
    """Give rosbags' readers the bounded decompressors: they decompress each chunk whole
    (bz2, lz4, zstd) however large it grows, and ingestion reads a bag with them, in staging
    processes even before :func:`check_mcap` has seen the file. rosbags looks them up by
    compression name in these module tables when it reads a chunk (ROS 1: when it opens the
    bag), so replacing the entries reaches every reader in the process."""
    for name in ("bz2", "lz4"):
        rosbag1_reader.decompressors[name] = partial(inflate, name)
    for name in ("lz4", "zstd"):
        rosbag2_mcap.DECOMPRESSORS[name] = partial(inflate_declared, name)


_bound_rosbags()


class MissingDefinition(Exception):
    """A message type neither the bag nor rosbags' bundled typestore defines (or the bag's
    definition does not parse)."""

    def __init__(self, topic: str, msgtype: str, reason: str) -> None:
        super().__init__(f"topic {topic!r}: no usable definition of {msgtype!r}: {reason}")
        self.topic = topic
        self.msgtype = msgtype
        self.reason = reason


class MessageUndecodable(Exception):
    """One message's bytes do not decode with its type's definition."""

    def __init__(self, topic: str, msgtype: str, t_ns: int, reason: str) -> None:
        super().__init__(f"topic {topic!r} ({msgtype}) at t={t_ns}: cannot decode: {reason}")
        self.topic = topic
        self.msgtype = msgtype
        self.t_ns = t_ns
        self.reason = reason


@dataclass
class BagConnection:
    """One (topic, message type) pair of a bag, over all its storage files and publishers."""

    topic: str
    msgtype: str
    definition: str
    definition_format: Literal["msg", "idl", "none"]
    count: int
    definition_source: str | None = None
    """``bag``, or the bundled typestore used (``ros1_noetic``, ``ros2_humble``); None if none."""
    problem: str | None = None
    """Why this connection's messages cannot be decoded; None when they can."""
    typestore: Typestore | None = field(default=None, repr=False, compare=False)

    def summary(self) -> dict[str, Any]:
        return {
            "topic": self.topic,
            "msgtype": self.msgtype,
            "count": self.count,
            "definition": self.definition,
            "definition_format": self.definition_format,
            "definition_source": self.definition_source,
            "problem": self.problem,
        }


RawMessage = tuple[BagConnection, int, bytes]
Window = tuple[int | None, int | None]
"""Receive times in nanoseconds: messages from the first (included) to the second (excluded);
None leaves that side open."""


def detect_format(path: Path) -> BagFormat:
    """The bag format at ``path``, from its magic bytes (a directory is a ROS 2 bag)."""
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise BagUnreadable("a ROS 2 bag directory needs a metadata.yaml", path=path)
        return BagFormat.ROS2_DIRECTORY
    try:
        with path.open("rb") as stream:
            head = stream.read(16)
    except OSError as exc:
        raise BagUnreadable(f"cannot read: {exc.strerror}", path=path) from None
    if head.startswith(ROS1_MAGIC):
        return BagFormat.ROS1
    if head.startswith(MCAP_MAGIC):
        return BagFormat.MCAP
    if head.startswith(SQLITE_MAGIC):
        return BagFormat.SQLITE3
    if not head:
        raise BagCorrupt("the file is empty", path=path, offset=0)
    raise BagUnreadable("not a ROS 1 bag, an MCAP file or a rosbag2 sqlite3 file", path=path)


SUFFIXES = {BagFormat.ROS1: ".bag", BagFormat.MCAP: ".mcap", BagFormat.SQLITE3: ".db3"}


def check_mcap(path: Path) -> None:
    """Walk an MCAP file's records, checking CRCs and that each chunk holds as many messages as
    its message indexes list.

    rosbags skips over damaged bytes inside a chunk, losing its messages without a word (and
    rosbags' own writer stores neither CRCs nor message indexes, so the summary's message count
    is the last check left); this pass turns any damage it can see into :class:`BagCorrupt`
    with the offset of the chunk or record where it was found, when there is one. It costs one
    decompression of every chunk.

    Each chunk is decompressed within what it declares and :data:`MAX_CHUNK_BYTES`
    (:class:`BagUnreadable` past that, naming the chunk's offset and the sizes), never by
    the mcap library, which takes a chunk's word for its size (zstd) or takes no bound at all
    (lz4).
    """
    with path.open("rb") as stream:
        reader = StreamReader(stream, validate_crcs=True, emit_chunks=True)
        offset = 0
        chunk: tuple[int, int] | None = None
        indexed = in_chunks = 0
        try:
            for record in reader.records:
                if isinstance(record, Statistics) and record.message_count != in_chunks:
                    raise BagCorrupt(
                        f"the chunks hold {in_chunks} messages but the summary counts "
                        f"{record.message_count}",
                        path=path,
                    )
                if isinstance(record, MessageIndex):
                    indexed += len(record.records)
                else:
                    _check_chunk_count(chunk, indexed, path)
                    chunk, indexed = None, 0
                if isinstance(record, Chunk):
                    found = breakup_chunk(_inflated(record), validate_crc=True)
                    chunk = (offset, sum(isinstance(each, Message) for each in found))
                    in_chunks += chunk[1]
                offset = stream.tell()
            _check_chunk_count(chunk, indexed, path)
        except BagCorrupt:
            raise
        except ChunkTooLarge as exc:
            raise BagUnreadable(str(exc), path=path, offset=offset) from None
        except CRCValidationError as exc:
            raise BagCorrupt(str(exc), path=path, offset=offset) from None
        except Exception as exc:  # the mcap library and zstd raise anything on damaged bytes
            raise BagCorrupt(
                f"damaged MCAP record: {_reason(exc)}", path=path, offset=offset
            ) from None


def _inflated(chunk: Chunk) -> Chunk:
    """``chunk`` with its records decompressed within bounds (:func:`inflate_declared`)."""
    data = inflate_declared(chunk.compression, chunk.data, chunk.uncompressed_size)
    return replace(chunk, compression="", data=data)


def _check_chunk_count(chunk: tuple[int, int] | None, indexed: int, path: Path) -> None:
    if chunk is not None and indexed and chunk[1] != indexed:
        raise BagCorrupt(
            f"chunk holds {chunk[1]} messages but its index lists {indexed}",
            path=path,
            offset=chunk[0],
        )


class Bag:
    """An open bag: its connections and a time-ordered stream of its messages.

    Memory stays bounded by what the storage formats index (one small tuple per ROS 1 message,
    one chunk at a time), never by the messages themselves.
    """

    def __init__(self, path: Path, *, check: bool = True) -> None:
        self.path = path
        self.check = check
        """Whether MCAP files are walked for damage at open (:func:`check_mcap`); without it
        the caller checks them (:meth:`check_files`) before it trusts what it read."""
        self.format = detect_format(path)
        self._stack = ExitStack()
        self._is_ros1 = self.format is BagFormat.ROS1
        self._sources: list[tuple[Any, dict[int, BagConnection]]] = []
        self._decompress: Callable[[bytes], bytes] | None = None
        self.connections: list[BagConnection] = []
        self._by_key: dict[tuple[str, str], BagConnection] = {}
        self._digests: dict[tuple[str, str], str] = {}
        self._span = (0, 0)
        """Receive times of the first and the last message, as the bag's index has them."""

    @classmethod
    def open(cls, path: Path, *, check: bool = True) -> Self:
        bag = cls(path, check=check)
        try:
            bag._open()
        except BaseException:
            bag.close()
            raise
        return bag

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        self._stack.close()

    @property
    def message_count(self) -> int:
        return sum(connection.count for connection in self.connections)

    def _open(self) -> None:
        if self.format is BagFormat.ROS1:
            self._open_ros1()
        else:
            self._open_ros2()
        if len(self.connections) > MAX_TOPICS:
            raise BagUnreadable(
                f"holds {len(self.connections)} topics, more than the {MAX_TOPICS} a bag may",
                path=self.path,
            )
        for connection in self.connections:
            longest = max(len(connection.topic), len(connection.msgtype))
            if longest > MAX_NAME:
                raise BagUnreadable(
                    f"holds a topic or type name of {longest} characters, more than the "
                    f"{MAX_NAME} a bag's names may have",
                    path=self.path,
                )
        fallback = self._fallback_store()
        unrolled, text = unroll_budget(), text_budget()
        for connection in self.connections:
            digest = self._digests[(connection.topic, connection.msgtype)]
            _prepare(
                connection,
                digest,
                ros1=self._is_ros1,
                fallback=fallback,
                unrolled=unrolled,
                text=text,
            )

    def _fallback_store(self) -> tuple[str, Typestore]:
        store = FALLBACK_STORES[0 if self._is_ros1 else 1]
        return store.value, bundled_typestore(store)

    def _open_ros1(self) -> None:
        reader = Rosbag1Reader(self.path)
        try:
            reader.open()
        except Rosbag1ReaderError as exc:
            raise BagCorrupt(_reason(exc), path=self.path) from None
        self._stack.callback(reader.close)
        self._sources = [(reader, self._group(reader.connections))]
        self._span = (reader.start_time, reader.end_time)

    def _open_ros2(self) -> None:
        if self.check:
            self.check_files()
        reader = Rosbag2Reader(self._rosbags_path())
        try:
            reader.open()
        except Rosbag2ReaderError as exc:
            raise _classify_ros2(exc, self.path) from None
        except ChunkTooLarge as exc:
            raise self._refusal(exc, self.path, reader) from None
        except (TypesysError, KeyError, ValueError, OSError) as exc:
            raise BagCorrupt(_reason(exc), path=self.path) from None
        except Exception as exc:  # rosbags' readers parse with ord(), struct and asserts
            # on reads that may come back short: an MCAP cut after its magic raised
            # TypeError, a forged length MemoryError or struct.error. Only the bag's bytes
            # reach here, so each of these is damage, not a bug of ours.
            raise BagCorrupt(
                f"damaged or truncated ({type(exc).__name__}: {_reason(exc)})", path=self.path
            ) from None
        self._stack.callback(reader.close)
        self._span = (reader.start_time, reader.end_time)
        storage = reader.storage
        storages = getattr(storage, "storages", None)
        if storages is None:
            storages = [storage]
        elif storage.metadata.compression_mode == "message":
            self._decompress = partial(inflate, "zstd")
        self._sources = [(each, self._group(each.connections)) for each in storages]

    def check_files(self) -> None:
        """Walk the bag's MCAP files for damage (:func:`check_mcap`): what an open does
        unless told not to, for a caller that reads the bag while the check runs."""
        for storage_file in self._mcap_files():
            check_mcap(storage_file)

    def _mcap_files(self) -> list[Path]:
        if self.format is BagFormat.MCAP:
            return [self.path]
        if self.format is BagFormat.ROS2_DIRECTORY:
            return sorted(self.path.glob("*.mcap"))
        return []

    def _rosbags_path(self) -> Path:
        """rosbags picks its storage plugin by suffix; a bare file must carry the right one."""
        suffix = SUFFIXES.get(self.format)
        if suffix is not None and self.path.suffix != suffix:
            raise BagUnreadable(
                f"a {self.format.value} file must be named *{suffix} to be read", path=self.path
            )
        return self.path

    def _group(self, storage_connections: list[Connection]) -> dict[int, BagConnection]:
        """Map a storage's connection ids onto one :class:`BagConnection` per topic and type."""
        by_id: dict[int, BagConnection] = {}
        for raw in storage_connections:
            key = (raw.topic, raw.msgtype)
            connection = self._by_key.get(key)
            if connection is None:
                connection = BagConnection(
                    topic=raw.topic,
                    msgtype=raw.msgtype,
                    definition=raw.msgdef.data,
                    definition_format=_FORMATS[raw.msgdef.format],
                    count=0,
                )
                self._by_key[key] = connection
                self._digests[key] = raw.digest
                self.connections.append(connection)
            elif connection.definition_format == "none" and raw.msgdef.data:
                connection.definition = raw.msgdef.data
                connection.definition_format = _FORMATS[raw.msgdef.format]
            connection.count += raw.msgcount
            by_id[raw.id] = connection
        return by_id

    def raw_messages(
        self, topics: Collection[str] | None = None, window: Window | None = None
    ) -> Iterator[RawMessage]:
        """Messages as stored, in time order over every storage file.

        The whole bag is checked against its index's message counts at the end. A ``window``
        (start included, stop excluded, None unbounded) reads only the messages stamped in it:
        the caller then checks the counts over all its windows (:meth:`check_counts`).
        """
        start, stop = window if window is not None else (None, None)
        streams = []
        for source, by_id in self._sources:
            wanted = [
                raw
                for raw in source.connections
                if raw.id in by_id and (topics is None or raw.topic in topics)
            ]
            if wanted:
                streams.append(self._stream(source, wanted, by_id, start, stop, window is None))
        if len(streams) == 1:
            yield from streams[0]
        else:
            yield from heapq.merge(*streams, key=itemgetter(1))

    def time_windows(self, count: int) -> list[Window]:
        """``count`` consecutive windows of equal duration that together hold every message."""
        start, stop = self._span
        bounds: list[int | None] = [None]
        bounds += [start + (stop - start) * k // count for k in range(1, count)]
        bounds.append(None)
        return list(pairwise(bounds))

    def check_counts(self, read: Mapping[tuple[str, str], int]) -> None:
        """Raise :class:`BagCorrupt` unless ``read`` (messages read per topic and type, over
        all windows) is what the bag's index counts for each connection it names."""
        for key, count in read.items():
            connection = self._by_key[key]
            if count != connection.count:
                raise BagCorrupt(
                    f"topic {connection.topic!r}: read {count} messages where the bag's index "
                    f"counts {connection.count}",
                    path=self.path,
                )

    def _stream(
        self,
        source: Any,
        wanted: list[Connection],
        by_id: dict[int, BagConnection],
        start: int | None,
        stop: int | None,
        whole: bool,
    ) -> Iterator[RawMessage]:
        decompress = self._decompress
        path = Path(getattr(source, "path", self.path))
        read: Counter[int] = Counter()
        try:
            for raw, t_ns, data in source.messages(wanted, start, stop):
                read[raw.id] += 1
                payload = decompress(data) if decompress is not None else data
                yield by_id[raw.id], t_ns, payload
        except ChunkTooLarge as exc:
            raise self._refusal(exc, path, source) from None
        except (Rosbag1ReaderError, Rosbag2ReaderError, OSError, RuntimeError, ValueError) as exc:
            offset = _bad_ros1_chunk(source) if self._is_ros1 else None
            raise BagCorrupt(_reason(exc), path=path, offset=offset) from None
        except (AssertionError, KeyError, EOFError) as exc:
            raise BagCorrupt(f"damaged record ({_reason(exc)})", path=path) from None
        if not whole:
            return
        for raw in wanted:
            if read[raw.id] != raw.msgcount:
                raise BagCorrupt(
                    f"topic {raw.topic!r}: read {read[raw.id]} messages where the bag's index "
                    f"counts {raw.msgcount}",
                    path=path,
                )

    def _refusal(self, exc: ChunkTooLarge, path: Path, source: Any) -> BagError:
        """The refusal of a chunk rosbags was decompressing, naming the chunk's offset, which
        rosbags does not tell: a ROS 1 bag's chunks are tried again one by one, MCAP files
        walked by :func:`check_mcap`, which refuses the same chunk before decompressing it."""
        if self._is_ros1:
            return BagUnreadable(str(exc), path=path, offset=_bad_ros1_chunk(source))
        try:
            for each in [path] if path.suffix == ".mcap" else self._mcap_files():
                check_mcap(each)
        except BagError as found:
            return found
        return BagUnreadable(str(exc), path=path)

    def deserialize(self, connection: BagConnection, t_ns: int, raw: bytes) -> Any:
        """One message as rosbags deserializes it (a dataclass per message type)."""
        store = connection.typestore
        if store is None:
            raise MissingDefinition(connection.topic, connection.msgtype, connection.problem or "")
        try:
            if self._is_ros1:
                return store.deserialize_ros1(raw, connection.msgtype)
            return store.deserialize_cdr(raw, connection.msgtype)
        except MemoryError:
            raise  # the message is not bad, only too large for this process (see staging)
        except Exception as exc:  # rosbags' serde raises anything, from struct to numpy
            raise MessageUndecodable(
                connection.topic, connection.msgtype, t_ns, _reason(exc)
            ) from None


_FORMATS: dict[MessageDefinitionFormat, Literal["msg", "idl", "none"]] = {
    MessageDefinitionFormat.MSG: "msg",
    MessageDefinitionFormat.IDL: "idl",
    MessageDefinitionFormat.NONE: "none",
}


def _reason(exc: BaseException, limit: int = 300) -> str:
    """An exception's text on one line and bounded: rosbags quotes whole definitions."""
    text = " ".join(str(exc).split())
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    return text or type(exc).__name__


def _classify_ros2(exc: Rosbag2ReaderError, path: Path) -> BagError:
    text = _reason(exc)
    unsupported = ("not supported", "Unrecognized storage", "Profile is not")
    if any(marker in text for marker in unsupported):
        return BagUnreadable(text, path=path)
    return BagCorrupt(text, path=path)


def _bad_ros1_chunk(reader: Any) -> int | None:
    """The offset of the first ROS 1 chunk that does not decompress (the error path only)."""
    chunks = getattr(reader, "chunks", {})
    bio = getattr(reader, "bio", None)
    if bio is None:
        return None
    for position in sorted(chunks):
        chunk = chunks[position]
        try:
            bio.seek(chunk.datapos)
            chunk.decompressor(bio.read(chunk.datasize))
        except Exception:  # any failure marks this chunk as the damaged one
            return int(position)
    return None


def parse_definition(msgtype: str, definition: str, fmt: str) -> dict[str, Any]:
    """rosbags' field definitions for ``msgtype`` and its dependencies, from bag text."""
    if fmt == "msg":
        return service_event_types(msgtype, definition) or dict(
            get_types_from_msg(definition, msgtype)
        )
    types: dict[str, Any] = {}
    if definition.startswith(f"{IDL_SEPARATOR}IDL: "):
        for part in definition.split(IDL_SEPARATOR)[1:]:
            _, idl = part.split("\n", 1)
            types.update(get_types_from_idl(idl))
    else:
        types.update(get_types_from_idl(definition))
    return types


SERVICE_EVENT = re.compile(r"(?P<package>[^/]+)/srv/(?P<service>\w+)_Event")
"""The type of a service-introspection topic (``/<service>/_service_event``, ROS 2 Iron on)."""
SERVICE_HEADER = re.compile(rf"\A{IDL_SEPARATOR}SRV: [^\n]*\n")


def service_event_types(msgtype: str, definition: str) -> dict[str, Any] | None:
    """The types of a service's introspection events, when the bag holds the service's
    definition (``request --- response``) in place of the event's.

    rosbag2 writes service-event topics so (ros2/rosbag2#2365, open): the text, perhaps
    headed ``SRV: <service>``, parses as no message, and rosbags, rosbag2's own MCAP readers
    and mcap's decoders all refuse it, so every recorded service call was undecodable. The
    event is ROS 2's generated ``<Name>_Event``: ``service_msgs/msg/ServiceEventInfo info``,
    ``<Name>_Request[<=1] request``, ``<Name>_Response[<=1] response``, and
    ``ServiceEventInfo`` comes from rosbags' typestore (the same in Iron, Jazzy and Kilted).
    None for any other type or definition, the event's own included.
    """
    named = SERVICE_EVENT.fullmatch(msgtype)
    own, separator, dependencies = SERVICE_HEADER.sub("", definition, count=1).partition(
        "\n" + IDL_SEPARATOR
    )
    lines = own.splitlines()
    if named is None or "---" not in lines:
        return None
    cut = lines.index("---")
    service = msgtype.removesuffix("_Event")
    types: dict[str, Any] = dict(_service_event_info())
    for part, fields in (("Request", lines[:cut]), ("Response", lines[cut + 1 :])):
        parsed_as = f"{named['package']}/msg/{named['service']}_{part}"
        text = "\n".join(fields) + ("\n" + separator + dependencies if separator else "")
        parsed = dict(get_types_from_msg(text, parsed_as))
        types[f"{service}_{part}"] = parsed.pop(parsed_as)
        types.update(parsed)
    types[msgtype] = (
        [],
        [
            ("info", (Nodetype.NAME, "service_msgs/msg/ServiceEventInfo")),
            ("request", (Nodetype.SEQUENCE, ((Nodetype.NAME, f"{service}_Request"), 1))),
            ("response", (Nodetype.SEQUENCE, ((Nodetype.NAME, f"{service}_Response"), 1))),
        ],
    )
    return types


@cache
def _service_event_info() -> dict[str, Any]:
    """``service_msgs/msg/ServiceEventInfo`` and the type it holds, as rosbags defines them."""
    store = bundled_typestore(Stores.ROS2_JAZZY)
    names = ("service_msgs/msg/ServiceEventInfo", "builtin_interfaces/msg/Time")
    return {name: store.fielddefs[name] for name in names}


def unrolled_elements(types: Mapping[str, Any]) -> int:
    """The elements rosbags' code generation unrolls for ``types`` (rosbags' field
    definitions): the lengths of their fixed-size arrays of strings or of messages."""
    total = 0
    for _, fields in types.values():
        for _, (nodetype, detail) in fields:
            if nodetype != Nodetype.ARRAY:
                continue
            (element_type, element_detail), length = detail
            if element_type == Nodetype.NAME or element_detail[0] in ("string", "wstring"):
                total += length
    return total


def hollow_array(types: Mapping[str, Any], msgtype: str, *, ros1: bool) -> str | None:
    """The first field reachable from ``msgtype`` (``type.field``) that holds elements of a
    message serialising to no bytes (:func:`hollow_types`) as a decode cannot bound them:
    any fixed-size array of them, and in ROS 1 any sequence. Such elements cost the decode
    an object each and the message nothing, so a few bytes of message decode to as many as
    their counts say: a sequence's 4-byte length (``std_msgs/Empty[]`` of 0xFFFFFFFF made
    rosbags create 4.3 billion objects; 1,000,000 took 1.35 s), or nested fixed-size
    arrays, whose lengths multiply (a few lines of unrolled code each, see
    :data:`MAX_UNROLLED`). rosbags' CDR decoder checks a sequence's length against the
    bytes left (at least one per element), so in ROS 2 only fixed-size arrays are refused.
    None when there is no such field."""
    hollow = hollow_types(types, ros1=ros1)
    if not hollow:
        return None
    for name in _reachable(types, msgtype):
        for field_name, (nodetype, detail) in types[name][1]:
            if _unbounded_element(nodetype, detail, ros1=ros1) in hollow:
                return f"{name}.{field_name}"
    return None


def _unbounded_element(nodetype: Nodetype, detail: Any, *, ros1: bool) -> str | None:
    """The message type of a field's elements where their count is not bounded by the
    message's bytes should they take none: a fixed-size array's (its length is the
    definition's word), and in ROS 1 a sequence's too. None for any other field."""
    counted_by_definition = nodetype == Nodetype.ARRAY and detail[1] > 0
    counted_by_prefix = nodetype == Nodetype.SEQUENCE and ros1
    if not (counted_by_definition or counted_by_prefix):
        return None
    element_type, element = detail[0]
    return str(element) if element_type == Nodetype.NAME else None


PLACEHOLDER_FIELD = "structure_needs_at_least_one_member"
"""The ``uint8`` rosbags gives a message without fields: one byte in CDR (ROS 2's IDL does the
same), none in ROS 1, whose serializer skips it."""


def hollow_types(types: Mapping[str, Any], *, ros1: bool) -> set[str]:
    """The message types of ``types`` whose every message serialises to no bytes: in ROS 1
    one without fields, and in either generation one whose every field is such a message or
    a fixed-size array of length 0 or of such messages. Found from the leaves up (each type
    waits for the types its fields need), so a chain of types costs its length, never
    recursion."""
    waiting: dict[str, int] = {}
    users: dict[str, list[str]] = {}
    ready: list[str] = []
    for name, (_, fields) in types.items():
        needs = _hollow_if(fields, ros1=ros1)
        if needs is None:
            continue
        waiting[name] = len(needs)
        for each in needs:
            users.setdefault(each, []).append(name)
        if not needs:
            ready.append(name)
    hollow: set[str] = set()
    while ready:
        name = ready.pop()
        hollow.add(name)
        for user in users.get(name, ()):
            waiting[user] -= 1
            if not waiting[user]:
                ready.append(user)
    return hollow


def _hollow_if(fields: list[Any], *, ros1: bool) -> list[str] | None:
    """The message types that must all serialise to no bytes for a message of ``fields`` to
    (one entry per field that needs one); None when a field always takes bytes: a number, a
    string or a sequence (its length), or in CDR the placeholder of a message without
    fields."""
    if not fields:
        return [] if ros1 else None
    needs: list[str] = []
    for field_name, (nodetype, detail) in fields:
        if field_name == PLACEHOLDER_FIELD and ros1:
            continue
        if nodetype == Nodetype.NAME:
            needs.append(detail)
        elif nodetype == Nodetype.ARRAY:
            (element_type, element), length = detail
            if not length:
                continue
            if element_type != Nodetype.NAME:
                return None
            needs.append(element)
        else:
            return None
    return needs


def _reachable(types: Mapping[str, Any], msgtype: str) -> list[str]:
    """``msgtype`` and the types of ``types`` its fields lead to: a definition may carry
    others, which nothing decodes."""
    found = [msgtype] if msgtype in types else []
    seen = set(found)
    for name in found:
        for held in _held_types(types, name):
            if held not in seen:
                seen.add(held)
                found.append(held)
    return found


def _held_types(types: Mapping[str, Any], name: str) -> Iterator[str]:
    """The types of ``types`` that the fields of type ``name`` hold, alone or in arrays."""
    for _, (nodetype, detail) in types[name][1]:
        if nodetype == Nodetype.NAME:
            held = detail
        elif nodetype in (Nodetype.ARRAY, Nodetype.SEQUENCE) and detail[0][0] == Nodetype.NAME:
            held = detail[0][1]
        else:
            continue
        if held in types:
            yield held


def nesting_problem(types: Mapping[str, Any], msgtype: str) -> str | None:
    """Why rosbags cannot build ``msgtype`` from ``types``: a type holds itself (directly or
    through others), or types hold one another more than :data:`MAX_TYPE_DEPTH` deep. None
    when neither. Walked without recursion, each type once, its depth remembered for the
    other paths that reach it."""
    if msgtype not in types:
        return None
    below: dict[str, int] = {}
    """Each finished type's longest chain of types, itself included."""
    path = [msgtype]
    pending = [_held_types(types, msgtype)]
    while pending:
        held = next(pending[-1], None)
        if held is None:
            pending.pop()
            name = path.pop()
            below[name] = 1 + max((below[each] for each in _held_types(types, name)), default=0)
            continue
        if held in path:
            cycle = " -> ".join([*path[path.index(held) :], held])
            return f"the bag's definition has a type holding itself ({cycle}): no ROS message can"
        if len(path) + below.get(held, 1) > MAX_TYPE_DEPTH:
            return (
                f"the bag's definition nests types more than {MAX_TYPE_DEPTH} deep "
                f"(from {msgtype} through {held})"
            )
        if held not in below:
            path.append(held)
            pending.append(_held_types(types, held))
    return None


DefinitionKey = tuple[str, str, str, str | None]
"""A connection's message type, definition format and definition text, and its md5sum in a
ROS 1 bag (None in ROS 2): what a definition gives depends on both (the md5sum's check,
:func:`hollow_array`'s rules)."""


class DefinitionBudget:
    """What is left of one bag's bound on its definitions (:data:`MAX_UNROLLED` elements,
    :data:`MAX_DEFINITION_BYTES` of text): each distinct definition is charged once, in the
    order of its connections, before rosbags works on it, so a bag gives the same
    connections the same problems whatever a cache of another bag holds."""

    def __init__(self, limit: int, what: str, why: str) -> None:
        self.limit = limit
        self.left = limit
        self.what = what
        self.why = why
        self._charged: set[DefinitionKey] = set()

    def refusal(self, key: DefinitionKey, amount: int) -> str | None:
        """Charge a definition's ``amount`` unless it was; the problem if it does not fit."""
        if key in self._charged:
            return None
        if amount > self.left:
            return (
                f"the bag's definition holds {amount} {self.what}, more than the {self.left} "
                f"left of the {self.limit} a bag's definitions may hold ({self.why})"
            )
        self.left -= amount
        self._charged.add(key)
        return None


def unroll_budget() -> DefinitionBudget:
    return DefinitionBudget(
        MAX_UNROLLED,
        "elements of fixed-size arrays of strings or messages",
        "rosbags generates code for each",
    )


def text_budget() -> DefinitionBudget:
    return DefinitionBudget(
        MAX_DEFINITION_BYTES, "bytes of text", "rosbags parses about a megabyte a second"
    )


_STORES: dict[DefinitionKey, tuple[Typestore | str, int]] = {}
"""Typestores (or why none) per definition text, with the elements each unrolled."""


def _typestore_from_bag(
    connection: BagConnection,
    digest: str,
    *,
    ros1: bool,
    unrolled: DefinitionBudget,
    text: DefinitionBudget,
) -> Typestore | str:
    """A typestore holding only this definition (cached per text); an error text if it is
    longer than ``text`` has left, fails, holds an array a decode cannot bound
    (:func:`hollow_array`) or types in one another without end or past
    :data:`MAX_TYPE_DEPTH` (:func:`nesting_problem`), or would unroll more than ``unrolled``
    has left."""
    key = (
        connection.msgtype,
        connection.definition_format,
        connection.definition,
        digest if ros1 else None,
    )
    too_long = text.refusal(key, len(connection.definition.encode()))
    if too_long is not None:
        return too_long
    cached = _STORES.get(key)
    if cached is not None:
        return unrolled.refusal(key, cached[1]) or cached[0]
    result: Typestore | str
    elements = 0
    try:
        types = parse_definition(
            connection.msgtype, connection.definition, connection.definition_format
        )
        hollow = hollow_array(types, connection.msgtype, ros1=ros1)
        nesting = nesting_problem(types, connection.msgtype)
        if nesting is not None:
            result = nesting
        elif hollow is not None:
            result = _hollow_problem(hollow, ros1=ros1)
        else:
            elements = unrolled_elements(types)
            refused = unrolled.refusal(key, elements)
            if refused is not None:
                return refused
            result = _registered(types, connection.msgtype, digest if ros1 else "")
    except (TypesysError, KeyError, ValueError, IndexError) as exc:
        result = f"the bag's definition does not parse: {_reason(exc)}"
    if len(_STORES) > 256:
        _STORES.clear()
    _STORES[key] = (result, elements)
    return result


def _hollow_problem(field: str, *, ros1: bool) -> str:
    """The problem of a definition :func:`hollow_array` refuses, naming its ``field``."""
    return (
        f"the bag's definition holds {field}, an array of a message that serialises to no "
        f"bytes{' in ROS 1' if ros1 else ''}: a message of a few bytes could decode to "
        "billions of them"
    )


def _registered(types: Mapping[str, Any], msgtype: str, digest: str) -> Typestore | str:
    """A typestore of ``types`` with ``msgtype``'s (de)serializers built; the problem if a
    ROS 1 ``digest`` (empty: none to check) is not the definition's md5sum."""
    store = bundled_typestore(Stores.EMPTY)
    store.register(dict(types))
    store.get_msgdef(msgtype)
    if digest and store.generate_msgdef(msgtype)[1] != digest:
        return f"the definition does not match its md5sum {digest}"
    return store


def _prepare(
    connection: BagConnection,
    digest: str,
    *,
    ros1: bool,
    fallback: tuple[str, Typestore],
    unrolled: DefinitionBudget,
    text: DefinitionBudget,
) -> None:
    if connection.definition_format != "none" and connection.definition.strip():
        found = _typestore_from_bag(connection, digest, ros1=ros1, unrolled=unrolled, text=text)
        if isinstance(found, str):
            connection.problem = found
            return
        connection.typestore, connection.definition_source = found, "bag"
    else:
        name, store = fallback
        connection.definition_format = "none"
        if connection.msgtype not in store.fielddefs:
            connection.problem = (
                f"the bag carries no definition of {connection.msgtype} and rosbags' "
                f"{name} typestore has none either"
            )
            return
        connection.typestore, connection.definition_source = store, name
        connection.definition = store.generate_msgdef(
            connection.msgtype, ros_version=1 if ros1 else 2
        )[0]
        connection.definition_format = "msg"
