"""An in-memory blob sink: the CIDs cas would give, without a cas."""

from __future__ import annotations

from collections.abc import Sequence

from robocloud.unixfs import import_bytes


class MemoryBlobs:
    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}

    def put(self, data: bytes) -> str:
        _, cid = import_bytes(data)
        self.files[str(cid)] = data
        return str(cid)

    def put_many(self, blobs: Sequence[bytes]) -> list[str]:
        return [self.put(data) for data in blobs]
