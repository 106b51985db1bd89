"""The disk's reserve: free space that the writes robots ask for may not take.

Without one, robots whose writes succeed fill the disk to its last byte, and then every signed
write fails on its nonce's journal line, the deletions and garbage collections that would free
space included: only the operator could mend it. The request guard keeps the reserve from
request bodies (:class:`~services.common.middleware.DiskReserveLayer`); work that writes long
after its request was answered, an ingest job staging and committing a bag's records, keeps
it too, between its own writes.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path


class ReserveReached(Exception):
    """A write would leave less than the reserve free."""

    def __init__(self, free_bytes: int, reserve_bytes: int, incoming: int) -> None:
        super().__init__(
            f"the service keeps {reserve_bytes} bytes of its disk free and has {free_bytes} free"
        )
        self.free_bytes = free_bytes
        self.reserve_bytes = reserve_bytes
        self.incoming = incoming


@dataclass(frozen=True)
class DiskReserve:
    directory: Path
    """A directory on the disk that the reserve is kept on: the service's data directory."""
    reserve_bytes: int
    """0: no reserve."""

    def free_bytes(self) -> int:
        return shutil.disk_usage(self.directory).free

    def require_room(self, incoming: int = 0) -> None:
        """Raise :class:`ReserveReached` unless ``incoming`` more bytes leave the reserve free.
        A ``statvfs``: a few microseconds, cheap enough to call between any two writes."""
        if not self.reserve_bytes:
            return
        free = self.free_bytes()
        if free - incoming < self.reserve_bytes:
            raise ReserveReached(free, self.reserve_bytes, incoming)
