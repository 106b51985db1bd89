"""Streaming file work through worker threads without blocking the event loop."""

from __future__ import annotations

from collections.abc import AsyncGenerator, Iterator

import anyio

BATCH_BYTES = 4 << 20


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


def first_error(error: BaseException) -> BaseException:
    """The first real exception inside (possibly nested) exception groups."""
    while isinstance(error, BaseExceptionGroup):
        error = error.exceptions[0]
    return error
