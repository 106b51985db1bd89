"""Streaming file work through worker threads without blocking the event loop.

A streamed answer holds memory for as long as it lasts: the batch read ahead and what the
connection has not taken yet, about 2.5 MiB in all when the client stops reading (100 such
connections to ``dag/export`` held 250 MiB; with 4 MiB batches, which streamed no faster than
1 MiB ones, 430 MiB). So every stream holds one of ``cas_max_streams`` turns (``streamed``),
and a client that stops reading is dropped after the send timeout (``services.common.server``).
"""

from __future__ import annotations

from collections.abc import AsyncGenerator, Callable, Iterator
from typing import Any

import anyio
from fastapi import Request
from fastapi.responses import StreamingResponse
from starlette.types import Receive, Scope, Send

from services.common.slots import Slots

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


class HeldStreamingResponse(StreamingResponse):
    """A streamed answer that gives its stream turn back when it ends, however it ends."""

    def __init__(
        self, content: AsyncGenerator[bytes, None], release: Callable[[], None], **kwargs: Any
    ) -> None:
        super().__init__(content, **kwargs)
        self._release = release

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self._release()


async def streamed(request: Request, chunks: Iterator[bytes], **response: Any) -> StreamingResponse:
    """The answer streaming ``chunks`` (as ``threaded_stream``) in one of the app's stream
    turns (``app.state.stream_slots``); ``SlotsBusy`` (503) when none came within its wait."""
    slots: Slots = request.app.state.stream_slots
    release = await slots.hold()
    try:
        body = await threaded_stream(chunks)
    except BaseException:
        release()
        raise
    return HeldStreamingResponse(body, release, **response)


def first_error(error: BaseException) -> BaseException:
    """The first real exception inside (possibly nested) exception groups."""
    while isinstance(error, BaseExceptionGroup):
        error = error.exceptions[0]
    return error
