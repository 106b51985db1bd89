"""Fetching a bag named by its CID from cas: a bag file, or a ROS 2 bag directory.

A ROS 2 bag is a flat directory: ``metadata.yaml`` beside one or more storage files (a split
recording has one per part). The directory is checked from its own block and its entries'
root blocks before a byte of content is fetched: a ``metadata.yaml``, no subdirectories, at
most ``max_entries`` entries, and a declared total within ``max_bytes``. Declarations are the
DAG's word, so each file is then fetched with what is left of ``max_bytes`` as its cap and
verified block by block by the SDK. Whatever fails removes everything fetched so far.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from robocloud.cas import Cas, ContentTooLargeError
from robocloud.cid import CID, DAG_PB, RAW
from robocloud.dagpb import Link
from robocloud.directory import check_name
from robocloud.errors import FormatError, NotFoundError, RobocloudError
from robocloud.unixfs import DIRECTORY, FILE, HAMT_SHARD, RAW_TYPE, UnixfsError, decode_node
from services.storage.bags import SUFFIXES, detect_format

METADATA = "metadata.yaml"


@dataclass(frozen=True)
class BagBounds:
    max_bytes: int
    """The whole bag: a file's size, or the sum of a directory's files."""
    max_entries: int
    """Entries of a ROS 2 bag directory (``metadata.yaml`` and the storage files)."""


class BagNotFetchable(Exception):
    """A CID in cas that does not hold a bag: ``reason`` says why, ``entry`` names the
    directory entry at fault when there is one."""

    def __init__(self, cid: CID, reason: str, message: str, entry: str | None = None) -> None:
        super().__init__(f"{cid}: {message}")
        self.cid = str(cid)
        self.reason = reason
        self.entry = entry


class BagNotFound(Exception):
    """cas holds no such CID (or not every block of it)."""

    def __init__(self, cid: CID, what: str) -> None:
        super().__init__(f"cas does not hold {what}")
        self.cid = str(cid)


class BagTooLarge(Exception):
    def __init__(self, cid: CID, limit: int, declared: int | None = None) -> None:
        size = f"declares {declared} bytes" if declared is not None else "holds more"
        super().__init__(f"the bag {cid} {size}; a bag holds at most {limit} bytes")
        self.cid = str(cid)
        self.limit = limit


class BagCasUnavailable(Exception):
    """cas could not be reached, or answered what does not verify."""

    def __init__(self, cid: CID, reason: str) -> None:
        super().__init__(f"cas failed while fetching {cid}: {reason}")
        self.cid = str(cid)


@contextmanager
def _cas_errors(root: CID, limit: int) -> Iterator[None]:
    """The SDK's errors as the bag errors the route answers."""
    try:
        yield
    except NotFoundError as exc:
        raise BagNotFound(root, exc.message) from exc
    except ContentTooLargeError as exc:
        raise BagTooLarge(root, limit) from exc
    except RobocloudError as exc:
        raise BagCasUnavailable(root, str(exc)[:300]) from exc


def fetch_bag(cas: Cas, cid: CID, into: Path, bounds: BagBounds) -> Path:
    """Fetch the bag ``cid`` names into a new directory under ``into``: the path of the bag
    file (named with the suffix rosbags reads it by) or of the ROS 2 bag directory."""
    target = Path(tempfile.mkdtemp(dir=into, prefix=".bag-"))
    try:
        with _cas_errors(cid, bounds.max_bytes):
            entries = _directory_entries(cas, cid)
            if entries is None:
                return _fetch_file(cas, cid, target, bounds.max_bytes)
            return _fetch_directory(cas, cid, entries, target / "bag", bounds)
    except BaseException:
        shutil.rmtree(target, ignore_errors=True)
        raise


def _directory_entries(cas: Cas, cid: CID) -> list[Link] | None:
    """A directory's entries; None when ``cid`` is a file (raw, or a UnixFS file)."""
    if cid.codec == RAW:
        return None
    if cid.codec != DAG_PB:
        raise BagNotFetchable(cid, "not_unixfs", "neither a UnixFS file nor a directory")
    kind, node_links = _unixfs_kind(cas, cid)
    if kind in (FILE, RAW_TYPE):
        return None
    if kind == HAMT_SHARD:
        raise BagNotFetchable(cid, "sharded_directory", "a sharded directory is not a bag")
    if kind != DIRECTORY:
        raise BagNotFetchable(cid, "not_unixfs", "neither a UnixFS file nor a directory")
    return node_links


def _unixfs_kind(cas: Cas, cid: CID) -> tuple[int, list[Link]]:
    try:
        node, data = decode_node(cid, cas.block(cid))
    except FormatError as exc:
        raise BagNotFetchable(cid, "not_unixfs", f"not a UnixFS node: {exc}") from exc
    return data.type, node.links


def _fetch_file(cas: Cas, cid: CID, target: Path, max_bytes: int) -> Path:
    path = target / "bag.download"
    cas.get_to_file(cid, path, max_size=max_bytes)
    named = path.with_name(f"bag{SUFFIXES.get(detect_format(path), '')}")
    path.rename(named)
    return named


def _fetch_directory(
    cas: Cas, root: CID, entries: list[Link], bag: Path, bounds: BagBounds
) -> Path:
    _check_entries(cas, root, entries, bounds)
    bag.mkdir()
    remaining = bounds.max_bytes
    for link in entries:
        try:
            remaining -= cas.get_to_file(link.cid, bag / link.name, max_size=remaining)
        except NotFoundError as exc:
            raise BagNotFound(root, f"{link.name!r} ({link.cid}) of the bag") from exc
    return bag


def _check_entries(cas: Cas, root: CID, entries: list[Link], bounds: BagBounds) -> None:
    """Refuse what is not a flat bag directory within bounds, from the blocks alone."""
    if len(entries) > bounds.max_entries:
        raise BagNotFetchable(
            root,
            "too_many_entries",
            f"{len(entries)} entries; a bag directory holds at most {bounds.max_entries}",
        )
    names = [link.name for link in entries]
    if METADATA not in names:
        raise BagNotFetchable(
            root, "missing_metadata", f"a ROS 2 bag directory holds {METADATA}; this one does not"
        )
    declared = 0
    for link in entries:
        try:
            check_name(link.name)
        except UnixfsError as exc:
            raise BagNotFetchable(root, "invalid_entry", str(exc), entry=link.name[:256]) from exc
        declared += _declared_file_size(cas, root, link)
    if declared > bounds.max_bytes:
        raise BagTooLarge(root, bounds.max_bytes, declared)


def _declared_file_size(cas: Cas, root: CID, link: Link) -> int:
    """What an entry's root block says its file holds; a subdirectory is refused."""
    if link.cid.codec == RAW:
        return link.tsize
    if link.cid.codec == DAG_PB:
        try:
            _, data = decode_node(link.cid, cas.block(link.cid))
        except NotFoundError as exc:
            raise BagNotFound(root, f"{link.name!r} ({link.cid}) of the bag") from exc
        except FormatError:
            data = None
        if data is not None and data.type in (FILE, RAW_TYPE):
            return data.filesize or 0
    raise BagNotFetchable(
        root,
        "not_a_file",
        f"entry {link.name!r} is not a file: a ROS 2 bag directory is flat",
        entry=link.name,
    )
