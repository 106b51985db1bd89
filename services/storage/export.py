"""Records out as files others read: JSON lines, and MCAP that the mcap library (and Foxglove)
open directly.

Both are encoders fed records a batch at a time (``add``, then ``finish``), each batch answered
with the bytes it completed, so an export of a million records holds one MCAP chunk
(``chunk_size``) in memory, never the whole answer, and its caller decides how much work one
call does (the service: one query page).

MCAP layout: one schema per template (encoding ``jsonschema``, name the template id, the JSON
Schema of a whole record), one channel per (topic, template) with message encoding ``json``,
each message the record's JSON with ``log_time`` and ``publish_time`` = the record's ``t``.
The header's profile is empty: these are not ROS 2 CDR messages, so rosbags (which reads only
the ``ros2`` profile) cannot decode them; the mcap library can, and that is what tests use.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from typing import Any, Protocol

from mcap.writer import CompressionType, Writer

from robocloud.templates import ArrayOf, Container, FieldType, Scalar, Template

MCAP_LIBRARY = "robocloud"
JSON_SCHEMA = "https://json-schema.org/draft/2020-12/schema"


def record_json(record: dict[str, Any]) -> bytes:
    """A record's JSON, compact, keys sorted, ``t`` exact as in its canonical bytes."""
    return json.dumps(
        record, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False
    ).encode()


class Encoder(Protocol):
    """A file format written a batch of records at a time."""

    def add(self, records: Iterable[dict[str, Any]]) -> bytes:
        """The bytes that ``records`` completed (possibly none yet)."""
        ...

    def finish(self) -> bytes:
        """The bytes that close the file."""
        ...


class JsonLinesEncoder:
    """One record per line: each batch is its lines, and nothing closes the file."""

    def add(self, records: Iterable[dict[str, Any]]) -> bytes:
        return b"".join(record_json(record) + b"\n" for record in records)

    def finish(self) -> bytes:
        return b""


def field_schema(kind: FieldType) -> dict[str, Any]:
    """The JSON Schema of one template type (as ``robocloud.templates`` validates it)."""
    if isinstance(kind, Scalar):
        return _SCALARS[kind.kind]
    if isinstance(kind, ArrayOf):
        items = {"type": "array", "items": field_schema(kind.item)}
        offloaded = {"type": "string", "description": "CID of the array stored in cas"}
        return {"anyOf": [items, offloaded]}
    return _object(kind)


def _object(kind: Container | Template) -> dict[str, Any]:
    return {
        "type": "object",
        "properties": {name: field_schema(inner) for name, inner in kind.fields.items()},
        "required": list(kind.fields),
        "additionalProperties": False,
    }


def _range(item: str) -> dict[str, Any]:
    return {"type": "array", "items": {"type": item}, "minItems": 2, "maxItems": 2}


_SCALARS: dict[str, dict[str, Any]] = {
    "string": {"type": "string"},
    "int": {"type": "integer"},
    "float": {"type": "number"},
    "bool": {"type": "boolean"},
    "image": {"type": "string", "description": "CID of the image in cas"},
    "file": {"type": "string", "description": "CID of the file in cas"},
    "range<int>": _range("integer"),
    "range<float>": _range("number"),
}


def record_schema(template: Template) -> dict[str, Any]:
    """The JSON Schema of a whole record of ``template``."""
    return {
        "$schema": JSON_SCHEMA,
        "title": template.id,
        "description": template.description,
        "type": "object",
        "properties": {
            "template": {"const": template.id},
            "topic": {"type": "string"},
            "robot": {"type": "string"},
            "t": {"type": "integer", "minimum": 0},
            "data": _object(template),
        },
        "required": ["template", "topic", "robot", "t", "data"],
        "additionalProperties": False,
    }


class _Drain:
    """A write-only stream whose bytes are taken away as they come (the writer needs tell())."""

    def __init__(self) -> None:
        self._parts: list[bytes] = []
        self._position = 0

    def write(self, data: bytes) -> int:
        self._parts.append(bytes(data))
        self._position += len(data)
        return len(data)

    def tell(self) -> int:
        return self._position

    def flush(self) -> None:
        return None

    def take(self) -> bytes:
        taken = b"".join(self._parts)
        self._parts.clear()
        return taken


class McapEncoder:
    """An MCAP file whose bytes leave as each chunk closes: a batch is answered with the
    chunks it closed, so the bytes do not depend on how the records were batched."""

    def __init__(
        self,
        template_of: Callable[[str], Template],
        *,
        chunk_size: int = 1 << 20,
        compression: CompressionType = CompressionType.ZSTD,
    ) -> None:
        self._template_of = template_of
        self._drain = _Drain()
        self._writer = Writer(
            self._drain,  # type: ignore[arg-type]
            chunk_size=chunk_size,
            compression=compression,
        )
        self._writer.start(profile="", library=MCAP_LIBRARY)
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._sequence = 0

    def add(self, records: Iterable[dict[str, Any]]) -> bytes:
        for record in records:
            self._writer.add_message(
                channel_id=self._channel(record["template"], record["topic"]),
                log_time=record["t"],
                publish_time=record["t"],
                data=record_json(record),
                sequence=self._sequence,
            )
            self._sequence = (self._sequence + 1) & 0xFFFFFFFF
        return self._drain.take()

    def finish(self) -> bytes:
        self._writer.finish()  # type: ignore[no-untyped-call]
        return self._drain.take()

    def _channel(self, template_id: str, topic: str) -> int:
        """The channel of (topic, template), registered with its schema when first seen."""
        channel = self._channels.get((topic, template_id))
        if channel is None:
            channel = self._writer.register_channel(
                topic=topic,
                message_encoding="json",
                schema_id=self._schema(template_id),
                metadata={"template": template_id},
            )
            self._channels[topic, template_id] = channel
        return channel

    def _schema(self, template_id: str) -> int:
        schema = self._schemas.get(template_id)
        if schema is None:
            document = record_schema(self._template_of(template_id))
            schema = self._writer.register_schema(
                name=template_id,
                encoding="jsonschema",
                data=json.dumps(document, sort_keys=True).encode(),
            )
            self._schemas[template_id] = schema
        return schema
