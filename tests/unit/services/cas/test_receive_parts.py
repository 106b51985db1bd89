"""``receive_parts`` when its sink fails: the sink's own error comes out, whatever the race."""

from __future__ import annotations

import errno
import time
from collections.abc import AsyncIterator

import anyio
import pytest

from services.cas.uploads import BATCH_BYTES, receive_parts

BOUNDARY = b"parts-under-test"


class FullDisk:
    """A sink whose disk fills on its first write, slowly enough that the event loop is
    already waiting to hand over the next batch: the race a loaded machine produced."""

    def directory(self, name: str) -> None:
        raise AssertionError("no directory was sent")

    def begin(self, name: str) -> None:
        pass

    def write(self, data: bytes) -> None:
        time.sleep(0.2)
        raise OSError(errno.ENOSPC, "No space left on device")

    def end(self) -> None:
        pass


async def body(size: int) -> AsyncIterator[bytes]:
    yield (
        b"--" + BOUNDARY + b"\r\n"
        b'Content-Disposition: form-data; name="file"; filename="big"\r\n'
        b"Content-Type: application/octet-stream\r\n\r\n"
    )
    for _ in range(size // 65536):
        yield bytes(65536)
    yield b"\r\n--" + BOUNDARY + b"--\r\n"


def test_the_sinks_full_disk_comes_out_not_the_closed_stream_it_left() -> None:
    with pytest.raises(OSError, match="No space left on device") as raised:
        anyio.run(receive_parts, body(6 * BATCH_BYTES), BOUNDARY, FullDisk())
    assert raised.value.errno == errno.ENOSPC
