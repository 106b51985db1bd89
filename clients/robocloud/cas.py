"""``Cas``: put and get content through a robocloud (or any kubo-compatible) gateway.

The robot trusts nothing but the CID. ``add`` computes the CID locally while it uploads and
refuses an answer that differs; ``get`` fetches a CAR and verifies every block against its
CID before reassembling the file, so a lying gateway can at worst withhold data, and
``max_size`` bounds what a DAG that expands (a few blocks linked thousands of times) may write.
"""

from __future__ import annotations

import hashlib
import io
import itertools
import os
import secrets
import shutil
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, TypeGuard
from urllib.parse import quote_plus

from robocloud import bounded_json
from robocloud.car import MAX_SECTION_BYTES, CarError, CarReader
from robocloud.cid import CID, DAG_PB, RAW, Block, CIDError, parse_cid
from robocloud.client import ServiceClient
from robocloud.dagpb import Link
from robocloud.directory import (
    BuiltDirectory,
    DirectoryBuilder,
    NotADirectory,
    PathError,
    check_name,
    list_entries,
    resolve,
)
from robocloud.errors import BadRequestError, FormatError, InvalidAnswerError, RobocloudError
from robocloud.partial import free_space_beside, written_whole
from robocloud.unixfs import (
    DEFAULT_MAX_LINKS,
    DIRECTORY,
    HAMT_SHARD,
    MAX_DAG_DEPTH,
    METADATA,
    PROFILES,
    READ_ALLOWANCE,
    SYMLINK,
    GetBlock,
    Importer,
    ImportParams,
    UnixfsError,
    assemble_file,
    decode_node,
    file_node,
    read_car_range,
    write_file,
)

READ_SIZE = 1 << 20
CAR_MEDIA_TYPE = "application/vnd.ipld.car"
RAW_MEDIA_TYPE = "application/vnd.ipld.raw"
Progress = Callable[[int], None]


class CasError(InvalidAnswerError):
    """The gateway's answer cannot be trusted: a CID mismatch, a bad or incomplete CAR."""


class ContentTooLargeError(RobocloudError):
    """A file is larger than the caller allows; nothing of it is left on disk.

    ``declared`` is the size the file's root block declares when that alone was over
    ``limit`` (refused before anything was written); None when the DAG turned out to hold
    more than ``limit`` bytes while it was being written.
    """

    def __init__(self, cid: CID, limit: int, declared: int | None = None) -> None:
        if declared is not None:
            message = f"{cid} declares {declared} bytes, more than the limit of {limit} bytes"
        else:
            message = f"{cid} holds more than the limit of {limit} bytes"
        super().__init__(message)
        self.cid = cid
        self.limit = limit
        self.declared = declared


class NotAFileError(RobocloudError):
    """The CID asked for is content that is not a file (a directory, a symbolic link): a
    verified fact about what was asked for, so the asker's mistake, not the gateway's."""

    def __init__(self, cid: CID, kind: str) -> None:
        super().__init__(f"{cid} is {kind}, not a file")
        self.cid = cid
        self.kind = kind


class NoSuchPathError(RobocloudError):
    """A path the verified directory ``cid`` does not hold (no such entry, or an entry on
    the way that is not a directory): a fact about what was asked for, as
    :class:`NotAFileError` is."""

    def __init__(self, cid: CID, path: str, reason: str) -> None:
        super().__init__(f"{cid}/{path}: {reason}")
        self.cid = cid
        self.path = path


class LocalContentError(RobocloudError, ValueError):
    """Content on this machine that cas cannot take as it is: a symbolic link, a name that
    is not UTF-8 (UnixFS names are text), a directory with no name of its own."""


_NOT_FILES = {
    DIRECTORY: "a directory",
    HAMT_SHARD: "a sharded directory",
    SYMLINK: "a symbolic link",
    METADATA: "a UnixFS metadata node",
}


def is_directory(refused: NotAFileError) -> bool:
    """Whether what :meth:`Cas.get_to_file` refused is a directory, plain or sharded."""
    return refused.kind in (_NOT_FILES[DIRECTORY], _NOT_FILES[HAMT_SHARD])


def _no_progress(_: int) -> None:
    return None


MAX_TREE_ENTRIES = 100_000
"""Entries (files and directories) :meth:`Cas.get_tree` writes at most: a directory is a
stranger's word, and each entry is a file or directory made on this machine."""


@dataclass(frozen=True)
class Tree:
    """What :meth:`Cas.get_tree` wrote."""

    files: int
    directories: int
    size: int


class _BlocksAsWalked:
    """A directory's CAR (``dag-scope=all``, depth first) read by a walk of the same tree.

    Each block the walk takes is the CAR's next one when the gateway ordered the CAR as the
    walk goes, which it does: one request for the whole tree. A block the CAR does not hold
    next comes from the gateway alone, verified against its CID: a block the CAR carried
    once and a second file needs again, or every block from where a gateway orders its CAR
    otherwise (or repeats blocks), so such a gateway costs requests, never correctness. The
    last block taken is kept: the walk looks at an entry's root before it reads the entry.
    """

    def __init__(self, blocks: Iterator[Block], fetch: GetBlock) -> None:
        self._blocks = blocks
        self._fetch = fetch
        self._head: Block | None = None
        self._last: Block | None = None

    def take(self, cid: CID) -> bytes:
        if self._last is not None and self._last.cid == cid:
            return self._last.data
        if self._head is None:
            self._head = next(self._blocks, None)
        if self._head is not None and self._head.cid == cid:
            block, self._head = self._head, None
        else:
            block = Block(cid, self._fetch(cid))
        self._last = block
        return block.data


@dataclass(frozen=True)
class _Written:
    """An entry the walk wrote: where, what it holds (itself, or a directory's whole
    subtree) and at which depth, so that a copy stays within the depth bound."""

    path: Path
    holds: Tree
    depth: int


class _TreeWalk:
    """A directory's entries written depth first into a local directory, within bounds.

    An entry whose CID the walk wrote before (a file, or a directory, no deeper than it was)
    is copied from there: a CAR carries its blocks once.
    """

    def __init__(
        self, blocks: _BlocksAsWalked, progress: Progress, max_size: int, max_entries: int
    ) -> None:
        self.blocks = blocks
        self.progress = progress
        self.max_size = max_size
        self.max_entries = max_entries
        self.tree = Tree(0, 0, 0)
        self._written: dict[CID, _Written] = {}

    def directory(self, cid: CID, into: Path, depth: int) -> None:
        if depth > MAX_DAG_DEPTH:
            raise CasError(f"{cid} is a directory deeper than {MAX_DAG_DEPTH} levels")
        self._count(directories=1)
        for link in self._entries(cid):
            self.entry(cid, link, into, depth)

    def _entries(self, cid: CID) -> Iterator[Link]:
        """The directory's entries as its blocks arrive, so that the entry bound stops a
        large sharded directory before all of it is read."""
        not_a_directory = NotADirectoryError(f"{cid} is not a directory")
        if cid.codec != DAG_PB:
            raise not_a_directory
        try:
            yield from list_entries(cid, self.blocks.take)
        except NotADirectory:
            raise not_a_directory from None
        except (UnixfsError, FormatError) as exc:
            raise CasError(f"refused the gateway's directory {cid}: {exc}") from exc

    def entry(self, directory: CID, link: Link, into: Path, depth: int) -> None:
        try:
            target = into / check_name(link.name)
        except UnixfsError as exc:
            raise CasError(f"the directory {directory}: {exc}") from None
        if target.exists():
            raise CasError(f"the directory {directory} names {link.name!r} twice")
        written = self._written.get(link.cid)
        if written is not None and depth <= written.depth:
            self._copy(link.cid, written, target)
            return
        before = self.tree
        root = Block(link.cid, self.blocks.take(link.cid))
        try:
            _refuse_what_is_not_a_file(root)
        except NotAFileError as exc:
            if not is_directory(exc):
                raise
            target.mkdir()
            self.directory(link.cid, target, depth + 1)
        else:
            self._file(root, target)
        now = self.tree
        holds = Tree(
            now.files - before.files, now.directories - before.directories, now.size - before.size
        )
        self._written[link.cid] = _Written(target, holds, depth)

    def _file(self, root: Block, target: Path) -> None:
        left = self.max_size - self.tree.size
        try:
            declared = file_node(root.cid, root.data).size
        except UnixfsError as exc:
            raise CasError(f"refused the gateway's root block {root.cid}: {exc}") from exc
        if declared > left:
            raise ContentTooLargeError(root.cid, left, declared)
        with written_whole(target, overwrite=False) as out:
            capped = _CappedWriter(out, root.cid, left)
            size = write_file(root.cid, self.blocks.take, capped, self.progress)
        self._count(files=1, size=size)

    def _copy(self, cid: CID, written: _Written, target: Path) -> None:
        holds = written.holds
        left = self.max_size - self.tree.size
        if holds.size > left:
            raise ContentTooLargeError(cid, left, holds.size)
        self._count(holds.files, holds.directories, holds.size)
        if written.path.is_dir():
            shutil.copytree(written.path, target)
        else:
            with written.path.open("rb") as source, written_whole(target, overwrite=False) as out:
                shutil.copyfileobj(source, out)
        self.progress(holds.size)

    def _count(self, files: int = 0, directories: int = 0, size: int = 0) -> None:
        tree = self.tree
        self.tree = Tree(tree.files + files, tree.directories + directories, tree.size + size)
        if self.tree.files + self.tree.directories > self.max_entries:
            raise CasError(f"the directory holds more than {self.max_entries} entries")


@dataclass(frozen=True)
class _Part:
    """One part of an upload: a file read from ``source`` (a path, or bytes held in memory),
    or a directory when it is None."""

    name: str
    source: Path | bytes | None


class _Multipart:
    """kubo's multipart/form-data body of an ``add``, whose bytes (and so its digest) are fixed
    upfront: a directory part before its entries, names escaped with Go's QueryEscape."""

    def __init__(self, parts: list[_Part]) -> None:
        self.parts = parts
        self.boundary = "robocloud-" + secrets.token_hex(16)
        self.heads = [self._head(part) for part in parts]
        self.tail = f"--{self.boundary}--\r\n".encode()
        self.length = len(self.tail) + sum(
            len(head) + self._size(part) + 2 for head, part in zip(self.heads, parts, strict=True)
        )

    def _head(self, part: _Part) -> bytes:
        kind = "application/x-directory" if part.source is None else "application/octet-stream"
        return (
            f"--{self.boundary}\r\n"
            f'Content-Disposition: form-data; name="file"; filename="{quote_plus(part.name)}"\r\n'
            f"Content-Type: {kind}\r\n\r\n"
        ).encode()

    @staticmethod
    def _size(part: _Part) -> int:
        if part.source is None:
            return 0
        if isinstance(part.source, bytes):
            return len(part.source)
        return part.source.stat().st_size

    @property
    def content_type(self) -> str:
        return f"multipart/form-data; boundary={self.boundary}"

    def sha256(self) -> str:
        """The body's digest, for the signature, read from the files without holding them."""
        digest = hashlib.sha256()
        for chunk in self.chunks(_no_progress, lambda _: None, lambda _name, _data: None):
            digest.update(chunk)
        return digest.hexdigest()

    def chunks(
        self,
        progress: Progress,
        on_part: Callable[[_Part], object],
        on_content: Callable[[_Part, bytes], object],
    ) -> Iterator[bytes]:
        for head, part in zip(self.heads, self.parts, strict=True):
            on_part(part)
            yield head
            for chunk in _contents(part.source):
                on_content(part, chunk)
                progress(len(chunk))
                yield chunk
            yield b"\r\n"
        yield self.tail


def _contents(source: Path | bytes | None) -> Iterator[bytes]:
    """A part's bytes in chunks of at most ``READ_SIZE``, a file's read as they go."""
    if isinstance(source, bytes):
        for start in range(0, len(source), READ_SIZE):
            yield source[start : start + READ_SIZE]
    elif source is not None:
        with source.open("rb") as handle:
            while chunk := handle.read(READ_SIZE):
                yield chunk


class _IteratorReader:
    """A read-only binary stream over an iterator of byte chunks (a streamed HTTP body)."""

    def __init__(self, chunks: Iterator[bytes]) -> None:
        self._chunks = chunks
        self._buffer = bytearray()

    def read(self, size: int = -1) -> bytes:
        while size < 0 or len(self._buffer) < size:
            chunk = next(self._chunks, None)
            if chunk is None:
                break
            self._buffer += chunk
        if size < 0:
            size = len(self._buffer)
        data = bytes(self._buffer[:size])
        del self._buffer[:size]
        return data


class Cas(ServiceClient):
    """The content-addressed store as a robot sees it."""

    default_service = "cas"

    def add_bytes(
        self, data: bytes, *, pin: bool = True, params: ImportParams | None = None
    ) -> CID:
        (cid,) = self.add_blobs([data], pin=pin, params=params)
        return cid

    def add_blobs(
        self, blobs: Sequence[bytes], *, pin: bool = True, params: ImportParams | None = None
    ) -> list[CID]:
        """Upload each of ``blobs`` as a file of its own in one request (``ipfs add`` of
        several files); their CIDs in order, each checked against the one computed here.

        A storage node offloads a laser scan's arrays, a value or two a message: one signed
        exchange for each cost more than staging the messages did.
        """
        if not blobs:
            return []
        params = params or ImportParams()
        parts = [_Part(str(index), blob) for index, blob in enumerate(blobs)]
        tree = _LocalImport(params)
        reported = dict(self._add(parts, tree, params, pin, _no_progress))
        for part in parts:
            if part.name not in reported:
                raise CasError(f"the gateway's add answer names no file {part.name}")
        return [tree.files[part.name].cid for part in parts]

    def add_file(
        self,
        path: Path,
        *,
        pin: bool = True,
        params: ImportParams | None = None,
        name: str | None = None,
        progress: Progress = _no_progress,
    ) -> CID:
        """Upload a file; return its CID once the gateway's answer matches the local one.

        The local CID is computed from the bytes as they are sent, so the robot hashes its
        file while the gateway works on the previous chunk.
        """
        params = params or ImportParams()
        part = _Part(name or _part_name(path), path)
        tree = _LocalImport(params)
        reported = self._add([part], tree, params, pin, progress)[-1][1]
        expected = tree.files[part.name].cid
        if reported != expected:
            raise CasError(f"the gateway says {reported}, but the file's CID is {expected}")
        return expected

    def add_directory(
        self,
        path: Path,
        *,
        pin: bool = True,
        params: ImportParams | None = None,
        hidden: bool = False,
        progress: Progress = _no_progress,
    ) -> CID:
        """Upload a directory as ``ipfs add -r`` does; its CID once the gateway's matches ours.

        Entries whose names start with ``.`` are left out unless ``hidden`` (kubo's default
        too); a symbolic link is refused, as robocloud does not store UnixFS symlinks.
        """
        params = params or ImportParams()
        parts = _directory_parts(path, hidden)
        root_name = parts[0].name
        tree = _LocalImport(params)
        answers = self._add(parts, tree, params, pin, progress)
        expected = tree.directories()[root_name].link.cid
        reported = answers[-1][1]
        if answers[-1][0] != root_name or reported != expected:
            raise CasError(f"the gateway says {reported}, but the directory's CID is {expected}")
        return expected

    def _add(
        self,
        parts: list[_Part],
        tree: _LocalImport,
        params: ImportParams,
        pin: bool,
        progress: Progress,
    ) -> list[tuple[str, CID]]:
        """Send ``parts``, importing them locally as they go; check every file's CID."""
        body = _Multipart(parts)
        response = self.request(
            "POST",
            "/api/v0/add",
            params={**_import_options(params), "pin": str(pin).lower()},
            content=body.chunks(progress, tree.begin, tree.feed),
            content_sha256=body.sha256(),
            headers={"Content-Type": body.content_type, "Content-Length": str(body.length)},
        )
        tree.finish_file()
        answers = []
        for line in response.content.splitlines():
            if not line.strip():
                continue
            try:
                entry = _json_line(line)
                answers.append((str(entry["Name"]), parse_cid(entry["Hash"], "Hash")))
            except (KeyError, TypeError, FormatError) as exc:
                raise CasError(
                    f"the gateway's add answer has no valid Hash ({exc}): {line[:200]!r}"
                ) from exc
        if not answers:
            raise CasError("the gateway's add answer is empty")
        for name, reported in answers:
            expected = tree.files.get(name)
            if expected is not None and reported != expected.cid:
                raise CasError(f"the gateway says {reported}, but the file's CID is {expected.cid}")
        return answers

    def get(self, cid: CID | str, *, max_size: int | None = None) -> bytes:
        """The verified content of a file, held in memory: at most ``max_size`` bytes, by
        default ``max_answer_bytes`` as for any answer read whole (``ContentTooLargeError``
        past it). A DAG expands, a few blocks linked thousands of times, so a kilobyte CAR
        could otherwise fill the robot's memory."""
        root = _as_cid(cid)
        limit = self.max_answer_bytes if max_size is None else max_size
        out = io.BytesIO()
        with self.translate_errors("GET", f"{self.base_url}/ipfs/{root}"):
            self._check_declared_size(root, limit)
            self._download(root, _CappedWriter(out, root, limit), _no_progress)
        return out.getvalue()

    def get_to_file(
        self,
        cid: CID | str,
        path: Path,
        progress: Progress = _no_progress,
        *,
        max_size: int | None = None,
        overwrite: bool = True,
    ) -> int:
        """Fetch a file as a CAR, verify every block, and write its content to ``path``.

        The file appears under ``path`` only once all of it was verified; whatever fails
        (a lying gateway, ``max_size``, an interrupt) removes the partial file, a new one
        beside ``path`` that this call created (never a file or link already there). With
        ``max_size`` (by default the free space in ``path``'s directory, as ``robocloud get``
        has it: a DAG expands, so a kilobyte CAR could fill the disk), a root that declares
        more is refused before anything is written, and a DAG that holds more than it
        declares is stopped at the limit. Without ``overwrite``, an existing ``path`` is never
        replaced (``FileExistsError``), even by a file that appeared while downloading.
        """
        root = _as_cid(cid)
        if not overwrite and (path.exists() or path.is_symlink()):
            raise FileExistsError(f"{path} exists")
        url = f"{self.base_url}/ipfs/{root}"
        if max_size is None:
            max_size = free_space_beside(path)
        with self.translate_errors("GET", url):
            self._check_declared_size(root, max_size)
        with written_whole(path, overwrite=overwrite) as out, self.translate_errors("GET", url):
            return self._download(root, _CappedWriter(out, root, max_size), progress)

    def get_tree(
        self,
        cid: CID | str,
        path: Path,
        progress: Progress = _no_progress,
        *,
        max_size: int | None = None,
        max_entries: int = MAX_TREE_ENTRIES,
    ) -> Tree:
        """A directory, plain or HAMT-sharded, written to the new directory ``path`` as
        ``ipfs get`` writes one, every block verified.

        Each entry's name is one path segment, never ``.`` or ``..``, so no directory makes
        this write outside ``path``; it holds at most ``max_entries`` entries and
        ``max_size`` bytes of files in all (by default the free space in ``path``'s
        directory), each file checked against what is left. The tree is written under a
        hidden name beside ``path`` and moved there once whole: a failure removes it. An
        existing ``path`` is never replaced (``FileExistsError``). A symbolic link or a
        metadata node in the tree is :class:`NotAFileError` (robocloud writes neither); a
        ``cid`` that is not a directory, ``NotADirectoryError``.
        """
        root = _as_cid(cid)
        if path.exists() or path.is_symlink():
            raise FileExistsError(f"{path} exists")
        if max_size is None:
            max_size = free_space_beside(path)
        partial = path.with_name(f".{path.name}.{secrets.token_hex(6)}.partial")
        partial.mkdir()
        url = f"{self.base_url}/ipfs/{root}"
        try:
            with (
                self.translate_errors("GET", url),
                self._car_blocks(root, str(root), **{"dag-scope": "all"}) as blocks,
            ):
                walk = _TreeWalk(
                    _BlocksAsWalked(blocks, self.block), progress, max_size, max_entries
                )
                walk.directory(root, partial, 0)
            if path.exists() or path.is_symlink():
                raise FileExistsError(f"{path} appeared while downloading")
            partial.rename(path)
        except BaseException:
            shutil.rmtree(partial, ignore_errors=True)
            raise
        return walk.tree

    def resolve(self, cid: CID | str, segments: Sequence[str]) -> CID:
        """What the path ``segments`` name under the directory ``cid``, each directory block
        on the way verified against its CID, so that no gateway can point the path
        elsewhere. A path the verified DAG does not hold is :class:`NoSuchPathError`."""
        root = _as_cid(cid)
        try:
            return resolve(root, list(segments), self.block).cid
        except PathError as exc:
            raise NoSuchPathError(root, "/".join(segments), str(exc)) from None
        except (UnixfsError, FormatError) as exc:
            raise CasError(f"refused the gateway's directory under {root}: {exc}") from exc

    def block(self, cid: CID | str, *, cached_only: bool = False) -> bytes:
        """One raw block from the gateway, verified against its CID.

        ``cached_only`` asks the gateway to answer from its own store (412 otherwise), as
        gateways ask each other so that two that list each other never bounce a miss around.
        """
        root = _as_cid(cid)
        url = f"/ipfs/{root}"
        headers = {"Accept": RAW_MEDIA_TYPE}
        if cached_only:
            headers["Cache-Control"] = "only-if-cached"
        with self.translate_errors("GET", f"{self.base_url}{url}"):
            response = self.request(
                "GET", url, params={"format": "raw"}, headers=headers, stream=True
            )
            data = bytearray()
            try:
                for chunk in response.iter_bytes(READ_SIZE):
                    data += chunk
                    if len(data) > MAX_SECTION_BYTES:
                        raise CasError(f"the gateway's block {root} exceeds {MAX_SECTION_BYTES}")
            finally:
                response.close()
        try:
            root.verify(bytes(data))
        except CIDError as exc:
            raise CasError(f"refused the gateway's block {root}: {exc}") from exc
        return bytes(data)

    def declared_size(self, cid: CID | str) -> int:
        """The size a file's root block declares (verified block; the DAG may still lie)."""
        root = _as_cid(cid)
        try:
            block = Block(root, self.block(root))
            _refuse_what_is_not_a_file(block)
            return file_node(root, block.data).size
        except (UnixfsError, FormatError) as exc:
            raise CasError(f"refused the gateway's root block {root}: {exc}") from exc

    def _check_declared_size(self, root: CID, limit: int) -> None:
        if root.codec == RAW:
            return
        declared = self.declared_size(root)
        if declared > limit:
            raise ContentTooLargeError(root, limit, declared)

    def _download(self, root: CID, out: BinaryIO, progress: Progress) -> int:
        """The file ``root`` from the gateway's CAR into ``out``."""
        with self._car_blocks(root, str(root)) as blocks:
            first = next(blocks, None)
            if first is not None:
                if first.cid == root:
                    _refuse_what_is_not_a_file(first)
                blocks = itertools.chain([first], blocks)
            return assemble_file(root, blocks, out, progress)

    @contextmanager
    def _car_blocks(self, root: CID, what: str, **params: str) -> Iterator[Iterator[Block]]:
        """The blocks of the gateway's CAR of ``root`` (``dag-scope=entity`` and ``params``),
        each hashed against its CID as it is read; a CAR or file the reader refuses is a
        ``CasError`` naming ``what`` was asked for. A CARv1 only, the one version the
        trustless gateway spec answers: a CARv2's padding would be read without bound before
        the first block."""
        response = self.request(
            "GET",
            f"/ipfs/{root}",
            params={"format": "car", "dag-scope": "entity", **params},
            headers={"Accept": f"{CAR_MEDIA_TYPE}; version=1; order=dfs; dups=n"},
            stream=True,
        )
        try:
            reader = CarReader(_IteratorReader(response.iter_bytes(READ_SIZE)), carv2=False)
            if root not in reader.roots:
                raise CasError(f"the gateway's CAR is rooted at {reader.roots}, not {root}")
            yield iter(reader)
        except (CarError, UnixfsError) as exc:
            raise CasError(f"refused the gateway's CAR for {what}: {exc}") from exc
        finally:
            response.close()

    def cat(self, cid: CID | str, offset: int = 0, length: int | None = None) -> bytes:
        """``length`` bytes of a file from ``offset`` (to its end when None), verified.

        kubo's ``cat`` answers whatever the node says; this asks the gateway for a CAR of just
        the range (``entity-bytes``), so every block is checked against its CID and the bytes
        are those ``cid`` commits to, as with :meth:`get`. The range is held in memory, at
        most ``max_answer_bytes`` of it (``ContentTooLargeError``). As with kubo, a range
        that is empty or starts past the end is no bytes; the file's size then comes from its
        verified root block.
        """
        root = _as_cid(cid)
        if offset < 0 or (length is not None and length < 0):
            raise ValueError(f"no bytes at offset {offset}, length {length}")
        limit = self.max_answer_bytes
        if length is not None and length > limit:
            raise ContentTooLargeError(root, limit)
        if length == 0:
            self.declared_size(root)
            return b""
        with self.translate_errors("GET", f"{self.base_url}/ipfs/{root}"):
            try:
                return self._range(root, offset, length, limit)
            except BadRequestError as exc:
                if exc.code != "invalid_entity_bytes" or offset < self.declared_size(root):
                    raise
                return b""

    def _range(self, root: CID, offset: int, length: int | None, limit: int) -> bytes:
        """The bytes of ``root`` from ``offset`` out of the gateway's CAR of that range."""
        span = f"{offset}:{'*' if length is None else offset + length - 1}"
        with self._car_blocks(root, f"{root} bytes {span}", **{"entity-bytes": span}) as blocks:
            out = bytearray()
            budget = limit + READ_ALLOWANCE
            for piece in read_car_range(root, blocks, offset, length, max_block_bytes=budget):
                out += piece
                if len(out) > limit:
                    raise ContentTooLargeError(root, limit)
            return bytes(out)

    def pin(self, cid: CID | str) -> None:
        self.request("POST", "/api/v0/pin/add", params={"arg": str(cid)}, idempotent=True)

    def unpin(self, cid: CID | str) -> None:
        self.request("POST", "/api/v0/pin/rm", params={"arg": str(cid)}, idempotent=True)

    def pin_share(self) -> PinShare:
        """This robot's pinned bytes and new bytes written in the last hour, with their bounds
        (robocloud's ``pin/share``)."""
        response = self.request("POST", "/api/v0/pin/share", idempotent=True)
        body = self.json_of(response)
        share = PinShare.from_answer(body)
        if share is None:
            raise self._invalid(response, "a pin/share answer of another shape")
        return share

    def pins(self) -> dict[str, dict[str, Any]]:
        """``{cid: {"Type": ..., "Owners": [...]}}`` as kubo's ``pin/ls`` answers."""
        response = self.request("POST", "/api/v0/pin/ls", signed=False, idempotent=True)
        body = self.json_of(response)
        keys = body.get("Keys", {}) if isinstance(body, dict) else None
        if not isinstance(keys, dict) or not all(
            isinstance(info, dict)
            and isinstance(info.get("Type", ""), str)
            and isinstance(info.get("Owners", []), list)
            and all(isinstance(owner, str) for owner in info.get("Owners", []))
            for info in keys.values()
        ):
            raise self._invalid(response, "a pin list that is not kubo's {Keys: {cid: {...}}}")
        return dict(keys)


@dataclass(frozen=True)
class PinShare:
    """A robot's part of a cas: the bytes its pins were charged and the new bytes it wrote
    in the last hour, each with the most it may (None: no bound, as for a storage node)."""

    robot: str
    pinned_bytes: int
    max_bytes: int | None
    written_bytes_last_hour: int
    max_written_bytes_per_hour: int | None

    @classmethod
    def from_answer(cls, body: Any) -> PinShare | None:
        """The share in a ``pin/share`` answer, None when the answer is not one."""
        if not isinstance(body, dict) or not isinstance(body.get("Robot"), str):
            return None
        pinned, written = body.get("PinnedBytes"), body.get("WrittenBytesLastHour")
        limits = body.get("MaxBytes"), body.get("MaxWrittenBytesPerHour")
        if not (_is_count(pinned) and _is_count(written)):
            return None
        if not all(limit is None or _is_count(limit) for limit in limits):
            return None
        return cls(body["Robot"], pinned, limits[0], written, limits[1])


def _is_count(value: Any) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


class _CappedWriter(io.BufferedIOBase, BinaryIO):
    """The file being assembled, refusing any write past ``limit`` bytes.

    The assembler appends, and reads back earlier bytes to replay a repeated block; so the
    count of appended bytes is the file's size, and the check happens before a byte of a
    write over the limit reaches the disk.
    """

    def __init__(self, out: BinaryIO, root: CID, limit: int) -> None:
        super().__init__()
        self._out = out
        self._root = root
        self._limit = limit
        self._size = 0

    def write(self, data: Any) -> int:
        size = len(data)
        if self._size + size > self._limit:
            raise ContentTooLargeError(self._root, self._limit)
        self._size += size
        return self._out.write(data)

    def read(self, size: int | None = -1) -> bytes:
        return self._out.read(-1 if size is None else size)

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._out.seek(offset, whence)

    def tell(self) -> int:
        return self._out.tell()

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True


class _LocalImport:
    """What the robot computes itself while it uploads: every file's CID, then directories."""

    def __init__(self, params: ImportParams) -> None:
        self.params = params
        self.files: dict[str, Link] = {}
        self.directory_names: list[str] = []
        self._importer: Importer | None = None
        self._current: _Part | None = None
        self._size = 0

    def begin(self, part: _Part) -> None:
        self.finish_file()
        if part.source is None:
            self.directory_names.append(part.name)
        else:
            self._importer, self._current, self._size = Importer(self.params), part, 0

    def feed(self, part: _Part, data: bytes) -> None:
        assert self._importer is not None
        self._size += sum(len(block.data) for block in self._importer.feed(data))

    def finish_file(self) -> None:
        if self._importer is None or self._current is None:
            return
        blocks, cid, _ = self._importer.finish()
        size = self._size + sum(len(block.data) for block in blocks)
        self.files[self._current.name] = Link(cid, self._current.name, size)
        self._importer = self._current = None

    def directories(self) -> dict[str, BuiltDirectory]:
        tree = DirectoryBuilder(
            self.params.cid_version, block_sized_shards=self.params.block_sized_shards
        )
        for name in self.directory_names:
            tree.add_directory(name)
        for name, link in self.files.items():
            tree.add_file(name, link.cid, link.tsize)
        return tree.finish()


def _refuse_what_is_not_a_file(root: Block) -> None:
    """``NotAFileError`` when the root block (hashed against its CID by the CAR reader) is a
    directory or another node that is not a file (a malformed one is a ``UnixfsError``)."""
    if root.cid.codec != DAG_PB:
        return
    _, unixfs = decode_node(root.cid, root.data)
    kind = _NOT_FILES.get(unixfs.type)
    if kind is not None:
        raise NotAFileError(root.cid, kind)


def _part_name(path: Path) -> str:
    """The name ``path`` has in UnixFS: its own, ``.`` and ``..`` resolved as ``ipfs add``
    does (``put .`` is the current directory under its name); refused when not UTF-8."""
    name = Path(os.path.abspath(path)).name
    if not name:
        raise LocalContentError(f"{path} has no name to store it under")
    try:
        name.encode()
    except UnicodeEncodeError as exc:
        raise LocalContentError(
            f"{os.fsencode(path)!r} has a name that is not UTF-8; UnixFS names are text"
        ) from exc
    return name


def _directory_parts(root: Path, hidden: bool) -> list[_Part]:
    """kubo's order: each directory before its entries, entries by name bytes."""
    if not root.is_dir():
        raise NotADirectoryError(f"{root} is not a directory")
    root_name = _part_name(root)
    parts = [_Part(root_name, None)]
    stack = [(root, root_name)]
    while stack:
        directory, name = stack.pop()
        children: list[tuple[Path, str]] = []
        for entry in sorted(directory.iterdir(), key=lambda item: os.fsencode(item.name)):
            if entry.name.startswith(".") and not hidden:
                continue
            if entry.is_symlink():
                raise LocalContentError(
                    f"{os.fsencode(entry)!r} is a symbolic link: robocloud stores no UnixFS "
                    "symlinks"
                )
            path = f"{name}/{_part_name(entry)}"
            if entry.is_dir():
                parts.append(_Part(path, None))
                children.append((entry, path))
            else:
                parts.append(_Part(path, entry))
        stack.extend(reversed(children))
    return parts


def _import_options(params: ImportParams) -> dict[str, str]:
    """kubo's add options for ``params``; kubo can only say a link count through a profile."""
    options = {
        "cid-version": str(params.cid_version),
        "raw-leaves": str(params.raw_leaves).lower(),
        "chunker": f"size-{params.chunk_size}",
    }
    if params.max_links == DEFAULT_MAX_LINKS and not params.block_sized_shards:
        return options
    for name, (_, _, _, links, exact) in PROFILES.items():
        if (links, exact) == (params.max_links, params.block_sized_shards):
            return {"profile": name, **options}
    raise ValueError(
        f"a gateway cannot be asked for {params.max_links} links per node; "
        f"use {DEFAULT_MAX_LINKS} or a profile's"
    )


def _as_cid(cid: CID | str) -> CID:
    return parse_cid(cid, "cid") if isinstance(cid, str) else cid


def _json_line(line: bytes) -> dict[str, Any]:
    value = bounded_json.loads(line)
    if not isinstance(value, dict):
        raise KeyError("Hash")
    return value
