"""Uploads: a multipart body streamed into one of three sinks, then committed or discarded.

The event loop receives the body (the request guard hashes it against the signed digest on
the way) and parses the multipart framing; a worker thread feeds the parts to the sink, which
stages blocks in a new pack. The two overlap through a queue of two batches, which bounds
memory whatever the upload size and keeps both cores busy. Only when the whole body arrived
does the sink commit; any failure before discards everything staged.

The sinks: :class:`FileAdder` (``add``: files through the UnixFS importer), :class:`CarImport`
(``dag/import``: CARs, every block verified) and :class:`BlockCollector` (``block/put``: raw
blocks as sent).
"""

from __future__ import annotations

import io
import threading
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

import anyio

from robocloud.car import MAX_ROOTS
from robocloud.cid import CID, DAG_PB, Block
from robocloud.dagpb import DagPbError, PBNode
from robocloud.directory import DirectoryBuilder, split_path
from robocloud.unixfs import Importer, ImportParams, UnixfsError
from services.cas.multipart import Event, MultipartParser, Part, PartData, boundary_of
from services.cas.shares import UNBOUNDED, Share
from services.cas.store import ContentStore, ImportedRoot
from services.common.pipeline import in_worker_thread

R = TypeVar("R")

BATCH_BYTES = 1 << 20
Command = tuple[str, bytes | str]
PIPE_BYTES = 2 * BATCH_BYTES
"""What a CAR part may hold between the thread receiving it and the thread reading it (with
the reader's buffer, ``READ_BUFFER_BYTES``, what an import holds beyond the upload's own two
batches): as fast as 4 MiB, and a hundred imports at once hold 225 MiB."""
READ_BUFFER_BYTES = 256 << 10


class DirectoryPart(ValueError):
    def __init__(self, name: str) -> None:
        super().__init__(f"part {name!r} is a directory; only files can be added")
        self.name = name


class InvalidPath(ValueError):
    """A part name that is not a safe relative path (``..``, absolute, empty segments)."""

    def __init__(self, name: str, reason: str) -> None:
        super().__init__(f"part {name[:200]!r}: {reason}")
        self.name = name


class TooManyParts(ValueError):
    def __init__(self, limit: int) -> None:
        super().__init__(f"the upload holds more than {limit} files and directories")
        self.limit = limit


class TooManyRoots(ValueError):
    """A ``dag/import`` whose CARs name more distinct roots, together, than one header may."""

    def __init__(self, count: int, limit: int) -> None:
        super().__init__(
            f"the CARs name at least {count} distinct roots together, more than {limit}"
        )
        self.count = count
        self.limit = limit


class NoFilePart(ValueError):
    def __init__(self) -> None:
        super().__init__("the multipart body holds no file")


class InvalidBlock(ValueError):
    """A ``block/put`` part that does not decode as the codec it was declared with."""

    def __init__(self, index: int, reason: str) -> None:
        super().__init__(f"block {index} is not valid dag-pb: {reason}")
        self.index = index


class PartSink(Protocol):
    """Receives the files (and directories) of a multipart body in order, in a worker thread."""

    def directory(self, name: str) -> None: ...

    def begin(self, name: str) -> None: ...

    def write(self, data: bytes) -> None: ...

    def end(self) -> None: ...


class Sink(PartSink, Protocol, Generic[R]):
    """A part sink that makes what it received visible (``commit``) or drops it."""

    def commit(self, owner: str, share: Share = UNBOUNDED) -> list[R]:
        """Store what was received, pinned for ``owner``, within its ``share``."""
        ...

    def discard(self) -> None: ...


async def upload(
    body: AsyncIterator[bytes],
    content_type: str | None,
    sink: Sink[R],
    owner: str,
    share: Share = UNBOUNDED,
) -> list[R]:
    """Stream a multipart ``body`` into ``sink`` and commit it for ``owner``, or store nothing.

    The discard runs on a worker thread: it waits for garbage collection's ``sweeping`` lock
    (held across fsyncs), unlinks a staged pack of up to the upload limit and joins a CAR
    reader, which on the event loop held every route meanwhile. It is shielded, since it
    must run in a cancelled request too (a cancel scope around it, a shutdown), or the pack
    stays until a restart.
    """
    try:
        await receive_parts(body, boundary_of(content_type), sink)
        return await anyio.to_thread.run_sync(sink.commit, owner, share)
    finally:
        with anyio.CancelScope(shield=True):
            await anyio.to_thread.run_sync(sink.discard)


def _apply(sink: PartSink, commands: list[Command]) -> None:
    for kind, value in commands:
        if kind == "data":
            assert isinstance(value, bytes)
            sink.write(value)
        elif kind == "end":
            sink.end()
        else:
            assert isinstance(value, str)
            (sink.begin if kind == "begin" else sink.directory)(value)


class _Batcher:
    """Turns parser events into commands for the sink, handed over about 1 MiB at a time.

    A directory part (kubo's ``application/x-directory``) is one ``directory`` command; its
    empty body is dropped.
    """

    def __init__(self) -> None:
        self.commands: list[Command] = []
        self.pending = 0
        self.parts = 0
        self._in_directory = False

    def take(self, events: list[Event]) -> None:
        for event in events:
            if isinstance(event, Part):
                self.parts += 1
                self._in_directory = event.is_directory
                self.commands.append(
                    ("directory" if event.is_directory else "begin", event.filename)
                )
            elif self._in_directory:
                continue
            elif isinstance(event, PartData):
                self.commands.append(("data", event.data))
                self.pending += len(event.data)
            else:
                self.commands.append(("end", b""))

    def flush(self) -> list[Command]:
        commands, self.commands, self.pending = self.commands, [], 0
        return commands


async def receive_parts(body: AsyncIterator[bytes], boundary: bytes, sink: PartSink) -> int:
    """Feed every part of a multipart body to ``sink``; returns how many there were."""
    parser = MultipartParser(boundary)
    batcher = _Batcher()

    async def command_batches() -> AsyncIterator[list[Command]]:
        async for chunk in body:
            batcher.take(parser.feed(chunk))
            if batcher.pending >= BATCH_BYTES:
                yield batcher.flush()
        parser.close()
        yield batcher.flush()

    await in_worker_thread(command_batches(), lambda commands: _apply(sink, commands))
    if batcher.parts == 0:
        raise NoFilePart()
    return batcher.parts


@dataclass(frozen=True)
class Added:
    """One line of an ``add`` answer: a file or a directory, its path, root and DAG size."""

    name: str
    cid: CID
    dag_size: int
    file_size: int | None = None
    """A file's size in bytes; None for a directory."""


class FileAdder:
    """``add``: files through the UnixFS importer, directories built as ``ipfs add -r`` does.

    Files are staged as they stream in; directories (kubo's ``application/x-directory``
    parts, and the parents a file's path implies) are built at commit, with
    ``wrap-with-directory`` adding one around everything.
    """

    def __init__(
        self,
        store: ContentStore,
        params: ImportParams,
        *,
        only_hash: bool,
        pin: bool,
        wrap: bool = False,
        max_parts: int = 250_000,
    ) -> None:
        self.store = store
        self.params = params
        self.only_hash = only_hash
        self.pin = pin
        self.wrap = wrap
        self.max_parts = max_parts
        self.staging = store.blocks.stage()
        self.files: list[Added] = []
        self.directories: list[str] = []
        self._importer: Importer | None = None
        self._name = ""
        self._dag_size = 0

    def directory(self, name: str) -> None:
        self._count()
        self.directories.append("/".join(_path(name)))

    def begin(self, name: str) -> None:
        self._count()
        self._name = "/".join(_path(name)) if name or self.wrap else ""
        self._importer = Importer(self.params)
        self._dag_size = 0

    def _count(self) -> None:
        if len(self.files) + len(self.directories) >= self.max_parts:
            raise TooManyParts(self.max_parts)

    def write(self, data: bytes) -> None:
        assert self._importer is not None, "write before begin"
        self._stage(self._importer.feed(data))

    def end(self) -> None:
        assert self._importer is not None, "end before begin"
        blocks, root, size = self._importer.finish()
        self._stage(blocks)
        self.files.append(Added(self._name or str(root), root, self._dag_size, size))
        self._importer = None

    def _stage(self, blocks: list[Block]) -> None:
        for block in blocks:
            self._dag_size += len(block.data)
            if not self.only_hash:
                self.staging.add(block.cid, block.data)

    def commit(self, owner: str, share: Share = UNBOUNDED) -> list[Added]:
        """Kubo's order: the files as they came, the directories after their contents.

        Every top-level item is pinned in one journal line: all or none, one fsync (they were
        pinned one a line, 2,003 fsyncs for 2,000 files, and a crash kept the first few).
        Each is charged its ``Size`` in the answer, the bytes of its DAG's blocks, a block
        repeated counting each time (not walked again: it would read the whole upload back).
        """
        directories = self._build_directories() if self._is_tree() else []
        if self.only_hash:
            return self.files + directories
        charges = {root.cid: root.dag_size for root in self._roots(directories)} if self.pin else {}
        self.store.commit_within(self.staging, charges, owner, share)
        return self.files + directories

    def _is_tree(self) -> bool:
        """Whether the upload holds directories: a directory part, a wrap, or a file's path
        alone (``d/x`` implies ``d`` even when the client sent no part for it)."""
        return bool(self.directories) or self.wrap or any("/" in f.name for f in self.files)

    def _build_directories(self) -> list[Added]:
        tree = DirectoryBuilder(
            self.params.cid_version, block_sized_shards=self.params.block_sized_shards
        )
        try:
            for path in self.directories:
                tree.add_directory(path)
            for added in self.files:
                tree.add_file(added.name, added.cid, added.dag_size)
            built = tree.finish()
        except UnixfsError as exc:
            raise InvalidPath("", str(exc)) from exc
        wanted = [path for path in sorted(built, key=_post_order) if path or self.wrap]
        for path in wanted:
            for block in built[path].blocks:
                self._stage([block])
        return [Added(path, built[path].link.cid, built[path].link.tsize) for path in wanted]

    def _roots(self, directories: list[Added]) -> list[Added]:
        """What an ``add`` pins: the wrapping directory, else every top-level item."""
        if self.wrap:
            return [directories[-1]]
        return [added for added in self.files + directories if "/" not in added.name]

    def discard(self) -> None:
        self.staging.discard()


def _path(name: str) -> tuple[str, ...]:
    try:
        return split_path(name)
    except UnixfsError as exc:
        raise InvalidPath(name, str(exc)) from exc


def _post_order(path: str) -> tuple[bytes, ...]:
    """Sort key putting every directory after those inside it, siblings by name bytes.

    0xff never occurs in UTF-8, so it sorts a directory after all its entries.
    """
    return (*(part.encode() for part in path.split("/") if part), b"\xff")


@dataclass
class ImportStats:
    """What ``dag/import?stats=true`` answers, counted as kubo counts: every block section of
    every CAR, one sent twice counted twice, whether the store held it or not."""

    blocks: int = 0
    bytes: int = 0

    def count(self, block: Block) -> None:
        self.blocks += 1
        self.bytes += len(block.data)


class PipeAborted(Exception):
    """The other end of a :class:`BytePipe` stopped: the upload failed on one side."""


class BytePipe(io.RawIOBase):
    """Bytes handed by one thread to another that reads them as a file, at most
    ``max_bytes`` held between them: ``put`` waits while the reader is behind.

    ``close_writing`` is the end of the bytes; ``stop_reading`` says the reader wants no
    more (what is put after it is dropped); ``abort`` stops both ends, each of which then
    raises ``PipeAborted``.
    """

    def __init__(self, max_bytes: int = PIPE_BYTES) -> None:
        super().__init__()
        self.max_bytes = max_bytes
        self._chunks: deque[memoryview] = deque()
        self._held = 0
        self._written = self._reading_stopped = self._aborted = False
        self._changed = threading.Condition()

    def readable(self) -> bool:
        return True

    def put(self, data: bytes) -> None:
        with self._changed:
            while self._held >= self.max_bytes and not (self._aborted or self._reading_stopped):
                self._changed.wait()
            if self._aborted:
                raise PipeAborted()
            if not self._reading_stopped and data:
                self._chunks.append(memoryview(data))
                self._held += len(data)
                self._changed.notify_all()

    def readinto(self, buffer: memoryview) -> int:  # type: ignore[override]
        with self._changed:
            while not (self._chunks or self._written or self._aborted):
                self._changed.wait()
            if self._aborted:
                raise PipeAborted()
            if not self._chunks:
                return 0
            chunk = self._chunks[0]
            size = min(len(buffer), len(chunk))
            buffer[:size] = chunk[:size]
            if size == len(chunk):
                self._chunks.popleft()
            else:
                self._chunks[0] = chunk[size:]
            self._held -= size
            self._changed.notify_all()
            return size

    def close_writing(self) -> None:
        with self._changed:
            self._written = True
            self._changed.notify_all()

    def stop_reading(self) -> None:
        with self._changed:
            self._reading_stopped = True
            self._chunks.clear()
            self._held = 0
            self._changed.notify_all()

    def abort(self) -> None:
        with self._changed:
            self._aborted = True
            self._changed.notify_all()


class CarImport:
    """``dag/import``: each CAR part read, every block verified and staged, as it arrives.

    A thread per part reads the CAR from a :class:`BytePipe` the part's bytes are put into:
    the part used to be spooled to a file and read back once whole, a second write and read
    of every byte (256 MiB imported in 1.9 s, now 1.5 s), and a bad block was found only
    after the whole part had arrived. The first error of the reader is the upload's, raised
    at the next ``write`` or at ``end``.

    The roots of all parts are one set in first-seen order (kubo's answer names each once),
    at most ``MAX_ROOTS`` of them, as one header may hold: 400 parts of 1,024 roots each
    were 409,600 roots walked, pinned and answered (488 MiB of memory, a 103 MiB answer).
    """

    def __init__(self, store: ContentStore, *, pin_roots: bool) -> None:
        self.store = store
        self.pin_roots = pin_roots
        self.staging = store.blocks.stage()
        self.roots: dict[CID, None] = {}
        self.stats = ImportStats()
        self._part: tuple[BytePipe, threading.Thread] | None = None
        """The part being received: the pipe its bytes go into, the thread reading them."""
        self._error: BaseException | None = None

    def directory(self, name: str) -> None:
        raise DirectoryPart(name)

    def begin(self, name: str) -> None:
        pipe = BytePipe()
        reader = threading.Thread(
            target=self._read_part, args=(pipe,), name="dag-import", daemon=True
        )
        self._part = (pipe, reader)
        reader.start()

    def _read_part(self, pipe: BytePipe) -> None:
        try:
            source = io.BufferedReader(pipe, READ_BUFFER_BYTES)
            self.store.import_car(self.staging, source, self._take_roots, self.stats.count)
        except PipeAborted:
            pass
        except BaseException as exc:
            self._error = exc
            pipe.abort()
        else:
            pipe.stop_reading()

    def write(self, data: bytes) -> None:
        assert self._part is not None, "write before begin"
        try:
            self._part[0].put(data)
        except PipeAborted:
            assert self._error is not None, "only the reader aborts a pipe while it is written"
            raise self._error from None

    def end(self) -> None:
        assert self._part is not None, "end before begin"
        pipe, reader = self._part
        pipe.close_writing()
        reader.join()
        self._part = None
        if self._error is not None:
            raise self._error

    def _take_roots(self, roots: list[CID]) -> None:
        """Add a header's roots to the set; ``TooManyRoots`` once they pass ``MAX_ROOTS``,
        before this part's blocks are read and before anything is stored or pinned."""
        self.roots.update(dict.fromkeys(roots))
        if len(self.roots) > MAX_ROOTS:
            raise TooManyRoots(len(self.roots), MAX_ROOTS)

    def commit(self, owner: str, share: Share = UNBOUNDED) -> list[ImportedRoot]:
        """Store the blocks; with ``pin_roots``, first walk the DAG of every root ``owner``
        does not pin yet (one too deep or malformed rejects the whole import), then pin the
        complete ones in one journal line; past ``owner``'s ``share`` the import is refused
        with nothing stored. Without ``pin_roots`` no root is walked or answered, as kubo.

        The walk reads this import's blocks and the store's, never a peer's (kubo's import
        is offline too): a CAR of one block linking to a DAG of any size at the peers had
        the cas fetch it all. The roots share one walk (``ContentStore.walked_to_pin``): a
        CAR naming one large DAG under many roots costs one pass over its blocks."""
        if not self.pin_roots:
            self.store.commit_within(self.staging, {}, owner, share)
            return []
        walked = list(
            self.store.walked_to_pin(list(self.roots), owner, share, self.staging, use_peers=False)
        )
        missing = {dag.root: dag.missing for dag in walked}
        charges = {dag.root: dag.size for dag in walked if dag.missing is None}
        self.store.commit_within(self.staging, charges, owner, share)
        return [ImportedRoot(root, _pin_error(root, missing.get(root))) for root in self.roots]

    def discard(self) -> None:
        """Stop a part's reader still running (the body failed half-way), then drop what
        was staged: the reader writes into the staging until it has stopped."""
        if self._part is not None:
            pipe, reader = self._part
            pipe.abort()
            reader.join()
        self.staging.discard()


def _pin_error(root: CID, missing: CID | None) -> str:
    if missing is None:
        return ""
    return f"block {missing} of the DAG is missing; {root} was not pinned"


class BlockCollector:
    """``block/put``: each part one block of ``codec``, checked, then all stored as one pack.

    A ``block/put`` body is small (its own body limit), so the blocks wait in memory.
    """

    def __init__(self, store: ContentStore, codec: int, *, pin: bool) -> None:
        self.store = store
        self.codec = codec
        self.pin = pin
        self.blocks: list[bytes] = []
        self._current = bytearray()

    def directory(self, name: str) -> None:
        raise DirectoryPart(name)

    def begin(self, name: str) -> None:
        self._current = bytearray()

    def write(self, data: bytes) -> None:
        self._current += data

    def end(self) -> None:
        data = bytes(self._current)
        if self.codec == DAG_PB:
            try:
                PBNode.decode(data)
            except DagPbError as exc:
                raise InvalidBlock(len(self.blocks), str(exc)) from exc
        self.blocks.append(data)

    def commit(self, owner: str, share: Share = UNBOUNDED) -> list[Block]:
        cids = self.store.put_blocks(self.blocks, self.codec, owner, pin=self.pin, share=share)
        return [Block(cid, data) for cid, data in zip(cids, self.blocks, strict=True)]

    def discard(self) -> None:
        self.blocks.clear()
