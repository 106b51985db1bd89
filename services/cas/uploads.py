"""Streaming uploads: multipart parsed as it arrives, content imported in a worker thread.

The event loop receives the body (the request guard hashes it against the signed digest on
the way) and parses the multipart framing; a worker thread imports the file bytes, hashing
and staging blocks. The two overlap through a queue of two batches, which bounds memory
whatever the upload size and keeps both cores busy.
"""

from __future__ import annotations

import tempfile
from collections.abc import AsyncIterator
from typing import Protocol

import anyio
from anyio.streams.memory import MemoryObjectReceiveStream

from robocloud.cid import CID
from services.cas.blockstore import Staging
from services.cas.multipart import Event, MultipartParser, Part, PartData
from services.cas.store import ContentStore
from services.cas.streams import first_error
from services.common.errors import BadRequest

BATCH_BYTES = 1 << 20
Command = tuple[str, bytes | str]


class PartSink(Protocol):
    """Receives the files of a multipart body in order, in a worker thread."""

    def begin(self, name: str) -> None: ...

    def write(self, data: bytes) -> None: ...

    def end(self) -> None: ...


def _apply(sink: PartSink, commands: list[Command]) -> None:
    for kind, value in commands:
        if kind == "data":
            assert isinstance(value, bytes)
            sink.write(value)
        elif kind == "begin":
            assert isinstance(value, str)
            sink.begin(value)
        else:
            sink.end()


async def _drain(receive: MemoryObjectReceiveStream[list[Command]], sink: PartSink) -> None:
    async with receive:
        async for commands in receive:
            await anyio.to_thread.run_sync(_apply, sink, commands)


class _Batcher:
    """Turns parser events into commands for the sink, handed over about 1 MiB at a time."""

    def __init__(self) -> None:
        self.commands: list[Command] = []
        self.pending = 0
        self.files = 0

    def take(self, events: list[Event]) -> None:
        for event in events:
            if isinstance(event, PartData):
                self.commands.append(("data", event.data))
                self.pending += len(event.data)
            elif isinstance(event, Part):
                self.commands.append(("begin", _file_name(event)))
                self.files += 1
            else:
                self.commands.append(("end", b""))

    def flush(self) -> list[Command]:
        commands, self.commands, self.pending = self.commands, [], 0
        return commands


def _file_name(part: Part) -> str:
    if part.content_type == "application/x-directory":
        raise BadRequest(
            f"part {part.filename!r} is a directory; only files can be added",
            code="unsupported_part",
            details={"part": part.filename},
        )
    return part.filename


async def receive_parts(body: AsyncIterator[bytes], boundary: bytes, sink: PartSink) -> int:
    """Feed every file part of a multipart body to ``sink``; returns how many there were."""
    parser = MultipartParser(boundary)
    batcher = _Batcher()
    send, receive = anyio.create_memory_object_stream[list[Command]](max_buffer_size=1)
    try:
        async with anyio.create_task_group() as group, send:
            group.start_soon(_drain, receive, sink)
            async for chunk in body:
                batcher.take(parser.feed(chunk))
                if batcher.pending >= BATCH_BYTES:
                    await send.send(batcher.flush())
            parser.close()
            await send.send(batcher.flush())
    except BaseExceptionGroup as group_error:
        raise first_error(group_error) from None
    if batcher.files == 0:
        raise BadRequest("the multipart body holds no file", code="no_file")
    return batcher.files


class CarSpool:
    """Spools each CAR part to a file, then stages its blocks, verifying every one."""

    def __init__(self, store: ContentStore, staging: Staging) -> None:
        self.store = store
        self.staging = staging
        self.roots: list[CID] = []
        self._file: tempfile._TemporaryFileWrapper[bytes] | None = None

    def begin(self, name: str) -> None:
        # Closed in end(), or with the staging directory when the upload fails.
        self._file = tempfile.NamedTemporaryFile(dir=self.staging.directory, suffix=".car")  # noqa: SIM115

    def write(self, data: bytes) -> None:
        assert self._file is not None, "write before begin"
        self._file.write(data)

    def end(self) -> None:
        assert self._file is not None, "end before begin"
        with self._file as spooled:
            spooled.flush()
            spooled.seek(0)
            self.roots.extend(self.store.import_car(self.staging, spooled))
        self._file = None
