"""Answers that outlive their route: a stream holds a turn until the server has sent it."""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

from fastapi.responses import StreamingResponse
from starlette.types import Receive, Scope, Send

from services.common.slots import Slots


class HeldStreamingResponse(StreamingResponse):
    """A streamed answer that gives its turn back when it ends, however it ends (sent, cut
    off, or its client gone)."""

    def __init__(
        self, content: AsyncIterator[bytes], release: Callable[[], None], **kwargs: Any
    ) -> None:
        super().__init__(content, **kwargs)
        self._release = release

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self._release()


async def stream_in_turn(
    slots: Slots, open_body: Callable[[], Awaitable[AsyncIterator[bytes]]], **response: Any
) -> StreamingResponse:
    """The answer streaming what ``open_body`` opens, in one of ``slots``' turns from before
    it opens until the answer ends; ``SlotsBusy`` (503) when no turn came within their wait."""
    release = await slots.hold()
    try:
        body = await open_body()
    except BaseException:
        release()
        raise
    return HeldStreamingResponse(body, release, **response)
