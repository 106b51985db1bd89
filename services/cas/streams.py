"""Streaming file work through worker threads without blocking the event loop.

A streamed answer holds memory for as long as it lasts: the batch read ahead and what the
connection has not taken yet, about 2.5 MiB in all when the client stops reading (100 such
connections to ``dag/export`` held 250 MiB; with 4 MiB batches, which streamed no faster than
1 MiB ones, 430 MiB). So every stream holds one of ``cas_max_streams`` turns (``gateway.streamed``),
and a client that stops reading is dropped after the send timeout (``services.common.server``).
"""

from __future__ import annotations

from collections.abc import AsyncGenerator, Iterator

import anyio

BATCH_BYTES = 1 << 20
STREAM_WAIT_S = 5.0


def _next_batch(chunks: Iterator[bytes]) -> list[bytes]:
    batch: list[bytes] = []
    size = 0
    for chunk in chunks:
        batch.append(chunk)
        size += len(chunk)
        if size >= BATCH_BYTES:
            break
    return batch


async def threaded_stream(chunks: Iterator[bytes]) -> AsyncGenerator[bytes, None]:
    """An async body over a blocking iterator, read a few MiB at a time in a worker thread.

    The first batch is read before this returns, so an error at the start (an unknown or
    corrupted root) still becomes a clean error response rather than a cut-off body. A block
    found corrupted later aborts the body: its bytes are never sent.
    """
    first = await anyio.to_thread.run_sync(_next_batch, chunks)

    async def generate() -> AsyncGenerator[bytes, None]:
        batch = first
        while batch:
            for chunk in batch:
                yield chunk
            batch = await anyio.to_thread.run_sync(_next_batch, chunks)

    return generate()
