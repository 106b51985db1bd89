"""What each fsync put on the disk, as a power cut would leave it: a file's size then, a
directory's names. Every process that imports this with ``ROBOCLOUD_TEST_SYNC_LOG`` set
appends a line per sync to that file, so a test sees the syncs of the staging processes as
well as the service's (they fork from a server that imports this first: :func:`preloaded`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

LOG_VARIABLE = "ROBOCLOUD_TEST_SYNC_LOG"


def _recording(sync: Callable[[int], None], log: str) -> Callable[[int], None]:
    def call(fd: int) -> None:
        sync(fd)
        path = os.readlink(f"/proc/self/fd/{fd}")
        state = sorted(os.listdir(path)) if os.path.isdir(path) else os.fstat(fd).st_size
        with open(log, "a") as lines:  # one short append: whole, whichever process writes
            lines.write(json.dumps([path, state]) + "\n")

    return call


def preloaded(context: Any) -> Any:
    """``context`` (a forkserver's) with this module imported by its server too."""
    from services.storage.staging import PRELOADED

    context.set_forkserver_preload([*PRELOADED, __name__])
    return context


def synced(log: Path) -> dict[str, int | list[str]]:
    """Per path, what its last sync left: a file's size, a directory's names."""
    found: dict[str, int | list[str]] = {}
    if log.exists():
        for line in log.read_text().splitlines():
            path, state = json.loads(line)
            found[path] = state
    return found


if os.environ.get(LOG_VARIABLE):
    os.fsync = _recording(os.fsync, os.environ[LOG_VARIABLE])
    os.fdatasync = _recording(os.fdatasync, os.environ[LOG_VARIABLE])
