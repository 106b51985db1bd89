"""Exports read back with the mcap library (and as JSON lines) equal the records put in."""

from __future__ import annotations

import io
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from robocloud.identity import Identity
from robocloud.templates import Template, parse_template, validate_record
from services.storage.bags import Bag
from services.storage.export import jsonl_stream, mcap_stream, record_schema
from services.storage.matcher import compile_converter, draft_template, record_topic
from tests.bagfactory import write_bag
from tests.blobs import MemoryBlobs


def bag_records(tmp_path: Path, count: int) -> tuple[list[dict[str, Any]], dict[str, Template]]:
    """Records as an ingest makes them, from a generated ROS 2 bag."""
    path = write_bag(tmp_path / "bag", "mcap", count)
    robot = Identity.generate().address
    blobs = MemoryBlobs()
    records: list[dict[str, Any]] = []
    templates: dict[str, Template] = {}
    with Bag.open(path) as bag:
        converters = {}
        for connection in bag.connections:
            assert connection.typestore is not None
            template = parse_template(draft_template(connection.typestore, connection.msgtype))
            templates[template.id] = template
            converters[connection.topic] = (
                template,
                compile_converter(template, connection.typestore, connection.msgtype),
            )
        for connection, t_ns, raw in bag.raw_messages():
            template, converter = converters[connection.topic]
            message = bag.deserialize(connection, t_ns, raw)
            record = {
                "template": template.id,
                "topic": record_topic(connection.topic),
                "robot": robot,
                "t": converter.record_time(message, t_ns),
                "data": converter.data(message, blobs),
            }
            validate_record(template, record)
            records.append(record)
    return records, templates


def test_mcap_export_reads_back_with_the_mcap_library(tmp_path: Path) -> None:
    records, templates = bag_records(tmp_path, 120)
    exported = b"".join(mcap_stream(records, templates.__getitem__, chunk_size=4096))
    reader = make_reader(io.BytesIO(exported))
    summary = reader.get_summary()
    assert summary is not None
    assert summary.statistics is not None
    assert summary.statistics.message_count == 120
    assert {c.topic for c in summary.channels.values()} == {"/imu", "/gps", "/camera/image_raw"}
    assert all(c.message_encoding == "json" for c in summary.channels.values())
    assert {s.name: s.encoding for s in summary.schemas.values()} == {
        "imu@1": "jsonschema",
        "nav_sat_fix@1": "jsonschema",
        "image@1": "jsonschema",
    }
    for schema in summary.schemas.values():
        assert json.loads(schema.data) == record_schema(templates[schema.name])
    read_back = []
    for schema, channel, message in reader.iter_messages(log_time_order=False):
        record = json.loads(message.data)
        assert message.log_time == message.publish_time == record["t"]
        assert channel.topic == record["topic"]
        assert schema is not None
        assert schema.name == record["template"]
        read_back.append(record)
    assert read_back == records
    assert make_reader(io.BytesIO(exported)).get_header().profile == ""


def test_record_schema_describes_the_template() -> None:
    template = parse_template(
        {
            "name": "pose",
            "version": 3,
            "fields": {
                "frame_id": "string",
                "position": {"container": {"x": "float", "n": "int", "ok": "bool"}},
                "snapshot": "image",
                "window": "range<int>",
                "ranges": {"array": "float"},
            },
            "description": "A pose.",
        }
    )
    schema = record_schema(template)
    data = schema["properties"]["data"]
    assert schema["title"] == "pose@3"
    assert schema["properties"]["template"] == {"const": "pose@3"}
    assert data["required"] == ["frame_id", "position", "snapshot", "window", "ranges"]
    assert data["additionalProperties"] is False
    assert data["properties"]["position"]["properties"] == {
        "x": {"type": "number"},
        "n": {"type": "integer"},
        "ok": {"type": "boolean"},
    }
    assert data["properties"]["window"]["minItems"] == 2
    assert data["properties"]["ranges"]["anyOf"][0] == {
        "type": "array",
        "items": {"type": "number"},
    }


def test_jsonl_export_is_one_record_per_line(tmp_path: Path) -> None:
    records, _ = bag_records(tmp_path, 50)
    exported = b"".join(jsonl_stream(records, batch_bytes=1024))
    lines = exported.split(b"\n")
    assert lines[-1] == b""
    assert [json.loads(line) for line in lines[:-1]] == records
    assert b"\n" not in lines[0]


def counting(records: list[dict[str, Any]], consumed: list[int]) -> Iterator[dict[str, Any]]:
    for record in records:
        consumed[0] += 1
        yield record


def test_exports_stream_while_records_arrive(tmp_path: Path) -> None:
    records, templates = bag_records(tmp_path, 400)
    consumed = [0]
    stream = mcap_stream(counting(records, consumed), templates.__getitem__, chunk_size=2048)
    next(stream)
    assert consumed[0] < len(records)
    rest = b"".join(stream)
    assert rest
    consumed = [0]
    lines = jsonl_stream(counting(records, consumed), batch_bytes=4096)
    next(lines)
    assert consumed[0] < len(records)


def test_empty_export_is_a_valid_mcap() -> None:
    exported = b"".join(mcap_stream([], lambda template_id: parse_template({})))
    summary = make_reader(io.BytesIO(exported)).get_summary()
    assert summary is not None
    assert summary.statistics is not None
    assert summary.statistics.message_count == 0
    assert b"".join(jsonl_stream([])) == b""
