"""Exports read back with the mcap library (and as JSON lines) equal the records put in."""

from __future__ import annotations

import asyncio
import io
import json
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import httpx
import pytest
from fastapi import FastAPI
from mcap.reader import make_reader

from robocloud.identity import Identity
from robocloud.templates import Template, parse_template, record_topic, validate_record
from services.common.slots import Slots
from services.storage import bags_api, queries
from services.storage.bags import Bag
from services.storage.export import Encoder, JsonLinesEncoder, McapEncoder, record_schema
from services.storage.matcher import compile_converter, draft_template
from services.storage.queries import Page, QueryEngine, RecordQuery
from services.storage.recordstore import RecordStore
from tests.bagfactory import write_bag
from tests.blobs import MemoryBlobs
from tests.unit.services.storage.conftest import (
    AUTHOR,
    REVIEWER,
    ROBOT_A,
    ROBOT_B,
    StoreFactory,
    state_record,
)

T = TypeVar("T")


def encoded(encoder: Encoder, records: Iterable[dict[str, Any]]) -> Iterator[bytes]:
    """The file of ``records``, fed one at a time, yielded as ``encoder`` completes bytes."""
    for record in records:
        if taken := encoder.add((record,)):
            yield taken
    yield encoder.finish()


def mcap_of(
    records: Iterable[dict[str, Any]], templates: dict[str, Template], chunk_size: int = 1 << 20
) -> Iterator[bytes]:
    return encoded(McapEncoder(templates.__getitem__, chunk_size=chunk_size), records)


def jsonl_of(records: Iterable[dict[str, Any]]) -> bytes:
    return b"".join(encoded(JsonLinesEncoder(), records))


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
    exported = b"".join(mcap_of(records, templates, chunk_size=4096))
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
    exported = jsonl_of(records)
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
    stream = mcap_of(counting(records, consumed), templates, chunk_size=2048)
    next(stream)
    assert consumed[0] < len(records)
    rest = b"".join(stream)
    assert rest
    consumed = [0]
    lines = encoded(JsonLinesEncoder(), counting(records, consumed))
    next(lines)
    assert consumed[0] < len(records)


def test_empty_export_is_a_valid_mcap() -> None:
    exported = b"".join(encoded(McapEncoder(lambda template_id: parse_template({})), []))
    summary = make_reader(io.BytesIO(exported)).get_summary()
    assert summary is not None
    assert summary.statistics is not None
    assert summary.statistics.message_count == 0
    assert jsonl_of([]) == b""


class TurnsCounted(Slots):
    """Query slots that count the pages each of their turns reads."""

    def __init__(self) -> None:
        super().__init__("query", 2, 5.0)
        self.pages: list[int] = []

    async def run_sync(self, work: Callable[[], T]) -> T:
        self.pages.append(0)
        return await super().run_sync(work)


def exported(store: RecordStore, slots: TurnsCounted, params: dict[str, str]) -> httpx.Response:
    """``GET /v1/export`` in process, counting each query page against the turn reading it."""
    app = FastAPI()
    app.include_router(bags_api.router)
    engine = QueryEngine(store)
    records = engine.records

    def counted(query: RecordQuery) -> Page:
        slots.pages[-1] += 1
        return records(query)

    engine.records = counted  # type: ignore[method-assign]
    app.state.queries = engine
    app.state.catalog = store.catalog
    app.state.query_slots = slots
    app.state.export_slots = Slots("export", 2, 5.0)

    async def get() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://storage") as client:
            return await client.get("/v1/export", params=params)

    return asyncio.run(get())


@pytest.mark.parametrize("robot", [REVIEWER, ROBOT_B])
@pytest.mark.parametrize("format", ["jsonl", "mcap"])
def test_each_query_slot_turn_of_an_export_reads_one_page(
    open_store: StoreFactory, monkeypatch: pytest.MonkeyPatch, robot: str, format: str
) -> None:
    """An export pulled records until an encoded chunk filled, in one query-slot turn: for a
    robot with no records (REVIEWER wrote none) every page scanned its ``MAX_SCANNED``
    documents and found nothing, so one turn scanned the whole template. A turn now reads
    one page, as ``GET /v1/records`` does, and the file is the same."""
    store = open_store()
    records = [state_record(t, robot=ROBOT_A if t % 2 else ROBOT_B) for t in range(100)]
    store.append(records, author=AUTHOR)
    whole = QueryEngine(store).records(RecordQuery(template="state@1", robot=robot, limit=100))
    expected = [stored.record for stored in whole.records]
    assert len(expected) == (50 if robot == ROBOT_B else 0)
    monkeypatch.setattr(queries, "MAX_SCANNED", 16)
    slots = TurnsCounted()
    answer = exported(store, slots, {"template": "state@1", "robot": robot, "format": format})
    assert answer.status_code == 200
    assert max(slots.pages) == 1
    assert sum(slots.pages) == 7  # 96 sealed records 16 a page, then the tail's 4
    if format == "jsonl":
        assert answer.content == jsonl_of(expected)
    else:
        templates = {"state@1": store.catalog.get("state@1").template}
        assert answer.content == b"".join(mcap_of(expected, templates))
