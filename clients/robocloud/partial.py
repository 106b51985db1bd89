"""Files a robot downloads appear whole or not at all.

A download written straight under its name leaves half a file behind when the service, the
network or a check fails midway, and the next reader takes it for the whole. So the bytes go
to a new hidden file beside the name, which replaces it only once everything arrived.
"""

from __future__ import annotations

import os
import secrets
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

PARTIAL_ATTEMPTS = 16


def free_space_beside(path: Path) -> int:
    """Bytes free in the directory ``path`` is written to: what a download writes at most
    unless told otherwise, since a stranger's DAG or export may expand without end."""
    return shutil.disk_usage(path.absolute().parent).free


@contextmanager
def written_whole(path: Path, *, overwrite: bool, mode: int = 0o666) -> Iterator[BinaryIO]:
    """A handle on a partial file beside ``path``, moved to ``path`` when the block ends
    normally and removed when it raises (an interrupt included).

    Without ``overwrite``, an existing ``path`` is never replaced (``FileExistsError``), even
    by a file that appeared meanwhile. ``mode`` (before the umask) is the file's from its
    creation, so a secret is never readable by others, not even half written.
    """
    partial, handle = _create_partial(path, mode)
    try:
        with handle:
            yield handle
        _publish(partial, path, overwrite)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


def _create_partial(path: Path, mode: int) -> tuple[Path, BinaryIO]:
    """A new hidden file beside ``path`` (``.NAME.<random>.partial``).

    Created with ``O_CREAT | O_EXCL | O_NOFOLLOW``: a file or symbolic link planted under
    the name (in a shared directory, by another user) is never opened, so nothing but a
    file this call created is ever written, truncated or removed. The name is random so a
    planted one cannot block the download either, nor can two downloads collide.
    """
    flags = os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
    for _ in range(PARTIAL_ATTEMPTS):
        partial = path.with_name(f".{path.name}.{secrets.token_hex(6)}.partial")
        try:
            descriptor = os.open(partial, flags, mode)
        except FileExistsError:
            continue
        return partial, os.fdopen(descriptor, "w+b")
    raise FileExistsError(f"no free name for a partial file beside {path}")


def _publish(partial: Path, path: Path, overwrite: bool) -> None:
    """Move the finished file into place; without ``overwrite``, atomically only if absent."""
    if overwrite:
        partial.replace(path)
        return
    os.link(partial, path)
    partial.unlink()
