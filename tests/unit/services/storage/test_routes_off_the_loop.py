"""Storage routes whose slow part (a disk write, a parse) is held: the service's other routes
answer meanwhile, as they do only when that part runs off the event loop."""

from __future__ import annotations

import asyncio
import hashlib
import json
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi import FastAPI
from fastapi.responses import JSONResponse

from robocloud import bounded_json
from robocloud.signing import VerifiedRequest
from robocloud.storage import Interval
from services.common.bodies import INLINE_JSON_BYTES
from services.common.errors import ServiceError
from services.common.slots import Slots
from services.storage import bags_api, ingest, knowledge_api, records_api
from services.storage.matcher import Bindings
from services.storage.queries import QueryEngine
from services.storage.settings import StorageSettings
from tests.held import Gate, answered_while_held, probed, signed_by
from tests.unit.services.storage.conftest import AUTHOR, ROBOT_A, StoreFactory, state_record
from tests.unit.services.storage.test_ingest import Node, authorship, bag


@pytest.fixture
def node(tmp_path: Path) -> Iterator[Node]:
    created = Node(tmp_path / "node")
    yield created
    created.close()


Request = tuple[str, str]
"""A method and a path."""


def in_process(app: FastAPI, verified: VerifiedRequest) -> httpx.AsyncClient:
    transport = httpx.ASGITransport(app=signed_by(app, verified))
    return httpx.AsyncClient(transport=transport, base_url="http://storage")


def test_polls_and_resends_answer_while_a_job_is_saved(
    node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The ingest thread saves job.json (two fsyncs) at each step, a batch of records each
    while committing, and held the jobs' lock meanwhile; ``GET /v1/jobs/{id}`` and a
    resend's check for the robot's unfinished job took that lock on the event loop, so
    a slow disk stopped every route of the service, and polls waited for the disk. They
    now answer from memory, the job as it is, while its save is held."""
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    gate = Gate()
    write = ingest.atomic_write

    def held_write(path: Path, data: bytes) -> None:
        if b'"status": "staging"' in data:
            gate.hold()
        write(path, data)

    monkeypatch.setattr(ingest, "atomic_write", held_write)
    upload = bag(tmp_path, "b.bag", 200, "ros1")
    body = upload.read_bytes()
    digest = hashlib.sha256(body).hexdigest()
    robot = authorship()
    job = node.jobs.submit(upload, f"upload:{digest}", robot)
    assert gate.entered.wait(10)

    app = FastAPI()
    app.include_router(bags_api.router)
    app.state.ingest_jobs = node.jobs
    app.state.bindings = node.bindings

    async def requests() -> tuple[dict[str, httpx.Response], dict[str, bool]]:
        verified = VerifiedRequest(robot.signer, 1, "n" * 16, digest, "storage@local")
        async with in_process(app, verified) as client:
            return await probed(
                gate,
                {
                    "poll": lambda: client.get(f"/v1/jobs/{job.id}"),
                    "resend": lambda: client.post(
                        "/v1/ingest",
                        content=body,
                        headers={"Content-Type": "application/octet-stream"},
                    ),
                    "bindings": lambda: client.get("/v1/bindings"),
                },
            )

    answers, answered_while_saving = asyncio.run(requests())

    assert answered_while_saving == {"poll": True, "resend": True, "bindings": True}
    poll, resend = answers["poll"], answers["resend"]
    assert poll.status_code == 200, poll.text
    assert (poll.json()["id"], poll.json()["status"]) == (job.id, "staging")
    assert resend.status_code == 202, resend.text
    assert (resend.json()["id"], resend.headers["location"]) == (job.id, f"/v1/jobs/{job.id}")
    assert answers["bindings"].json() == node.bindings.to_json()
    finished = node.jobs.wait(job.id, 60)
    assert (finished.status, finished.records_committed) == ("succeeded", 160), finished.error
    assert [path.parent.name for path in (node.root / "jobs").glob("*/job.json")] == [job.id]


@pytest.fixture
def records_app(open_store: StoreFactory, tmp_path: Path) -> FastAPI:
    """The records, templates and bindings routes over a store whose catalog has state@1."""
    store = open_store()
    app = FastAPI()
    app.include_router(records_api.router)
    app.include_router(bags_api.router)
    app.state.settings = StorageSettings()
    app.state.records = store
    app.state.catalog = store.catalog
    app.state.queries = QueryEngine(store)
    app.state.query_slots = Slots("query", 2, 5.0)
    app.state.bindings = Bindings(tmp_path / "bindings.json")
    return app


def held_then_probed(
    app: FastAPI, gate: Gate, held: Request, probe: Request, body: bytes = b""
) -> tuple[httpx.Response, httpx.Response]:
    """Send ``held`` (a method and path), and ``probe`` while ``gate`` holds it: both answers,
    once the probe was seen answered while the gate held."""

    async def requests() -> tuple[httpx.Response, dict[str, httpx.Response], dict[str, bool]]:
        verified = VerifiedRequest(ROBOT_A, 1, "n" * 16, hashlib.sha256(body).hexdigest(), "s")
        async with in_process(app, verified) as client:
            headers = {"Content-Type": "application/json"} if body else {}
            return await answered_while_held(
                gate,
                client.request(*held, content=body, headers=headers),
                {"probe": lambda: client.request(*probe)},
            )

    answer, probes, answered_while = asyncio.run(requests())
    assert answered_while == {"probe": True}
    return answer, probes["probe"]


def test_a_large_batch_of_records_is_parsed_off_the_event_loop(
    records_app: FastAPI, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A JSON array of records (64 MiB at most) was parsed on the event loop, about 3 s
    for the largest, every route of the service waiting; it is parsed on a thread now."""
    gate = Gate()
    monkeypatch.setattr(bounded_json, "loads", gate.wrap(bounded_json.loads))
    body = json.dumps([state_record(t) for t in range(1000)]).encode()
    assert len(body) > INLINE_JSON_BYTES

    stored, bindings = held_then_probed(
        records_app, gate, ("POST", "/v1/records"), ("GET", "/v1/bindings"), body
    )

    assert bindings.json() == {"topics": {}, "msgtypes": {}}
    assert stored.status_code == 201, stored.text
    assert stored.json()["count"] == 1000
    assert records_app.state.records.logs.size("state@1") == 1000


def test_a_template_is_read_off_the_event_loop(
    records_app: FastAPI, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The catalog's lock is held across the fsync of each template written, and
    ``GET /v1/templates/{id}`` took it on the event loop."""
    catalog = records_app.state.catalog
    gate = Gate()
    monkeypatch.setattr(catalog, "get", gate.wrap(catalog.get))

    template, bindings = held_then_probed(
        records_app, gate, ("GET", "/v1/templates/state@1"), ("GET", "/v1/bindings")
    )

    assert (template.json()["id"], template.json()["status"]) == ("state@1", "approved")
    assert bindings.json() == {"topics": {}, "msgtypes": {}}


def test_bindings_are_read_off_the_event_loop(
    records_app: FastAPI, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A bind holds the bindings' lock across its write (two fsyncs), and
    ``GET /v1/bindings`` took it on the event loop."""
    bindings: Bindings = records_app.state.bindings
    bindings.bind(template_id="state@1", topic="/state")
    gate = Gate()
    monkeypatch.setattr(bindings, "to_json", gate.wrap(bindings.to_json))

    listed, template = held_then_probed(
        records_app, gate, ("GET", "/v1/bindings"), ("GET", "/v1/templates/state@1")
    )

    assert listed.json() == {"topics": {"/state": "state@1"}, "msgtypes": {}}
    assert template.json()["id"] == "state@1"


def test_intervals_are_rendered_off_the_event_loop(
    records_app: FastAPI, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A state that toggles often in a wide window has up to a million intervals: their
    rendering and encoding took seconds of the event loop. Both happen in the query's turn."""
    records = [state_record(t, mode="docked" if t % 2 else "idle") for t in range(100)]
    records_app.state.records.append(records, author=AUTHOR)
    gate = Gate()
    monkeypatch.setattr(Interval, "to_json", gate.wrap(Interval.to_json))

    found, bindings = held_then_probed(
        records_app,
        gate,
        ("GET", "/v1/intervals?template=state@1&field=mode&value=docked"),
        ("GET", "/v1/bindings"),
    )

    assert found.status_code == 200, found.text
    assert found.headers["content-type"] == "application/json"
    answer = found.json()
    assert (answer["template"], answer["field"], answer["value"]) == ("state@1", "mode", "docked")
    assert [(i["enter"], i["exit"]) for i in answer["intervals"]] == [
        *((t, t + 1) for t in range(1, 99, 2)),
        (99, None),
    ]
    assert {i["robot"] for i in answer["intervals"]} == {ROBOT_A}
    assert bindings.json() == {"topics": {}, "msgtypes": {}}


async def refused(_: Any, error: Exception) -> JSONResponse:
    """The service's error handler, as much of it as a route's router served alone needs."""
    assert isinstance(error, ServiceError)
    return JSONResponse({"code": error.code, **error.details}, status_code=error.status)


def upload_while_held(
    node: Node, body: bytes, gate: Gate, settings: StorageSettings
) -> tuple[httpx.Response, httpx.Response, bool]:
    """``body`` sent to ``POST /v1/ingest`` of ``node`` until ``gate`` holds it, then
    ``GET /v1/bindings``: the upload's answer, the bindings' and whether they came while
    the gate held."""
    app = FastAPI()
    app.include_router(bags_api.router)
    app.add_exception_handler(ServiceError, refused)
    app.state.settings = settings
    app.state.ingest_jobs = node.jobs
    app.state.bindings = node.bindings
    digest = hashlib.sha256(body).hexdigest()
    verified = VerifiedRequest(authorship().signer, 1, "n" * 16, digest, "storage@local")

    async def requests() -> tuple[httpx.Response, dict[str, httpx.Response], dict[str, bool]]:
        async with in_process(app, verified) as client:
            held = client.post(
                "/v1/ingest", content=body, headers={"Content-Type": "application/octet-stream"}
            )
            return await answered_while_held(
                gate, held, {"bindings": lambda: client.get("/v1/bindings")}
            )

    sent, answers, answered_while = asyncio.run(requests())
    return sent, answers["bindings"], answered_while["bindings"]


def test_an_upload_is_hashed_and_written_off_the_event_loop(
    node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A bag upload (16 GiB at most) was hashed and written chunk by chunk on the event
    loop: a write the kernel throttled held every route. Its one batch is held here."""
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    body = bag(tmp_path, "b.bag", 200, "ros1").read_bytes()
    gate = Gate()
    monkeypatch.setattr(bags_api, "_spooled", gate.wrap(bags_api._spooled))

    sent, bindings, answered_while_writing = upload_while_held(node, body, gate, StorageSettings())

    assert answered_while_writing
    assert bindings.json() == node.bindings.to_json()
    assert sent.status_code == 202, sent.text
    assert sent.json()["bag"] == f"upload:{hashlib.sha256(body).hexdigest()}"
    finished = node.jobs.wait(sent.json()["id"], 120)
    assert (finished.status, finished.records_committed) == ("succeeded", 160), finished.error


def test_a_refused_upload_is_removed_off_the_event_loop(
    node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A bag refused after it arrived (here past the size limit; too many jobs, a cas fetch
    failed) was unlinked on the event loop: up to 16 GiB, or a directory of many files,
    holding every route. Its removal is held here; the spool is gone once it ends."""
    body = bag(tmp_path, "b.bag", 200, "ros1").read_bytes()
    gate = Gate()
    remove = shutil.rmtree
    incoming = node.root / "jobs" / ingest.INCOMING

    def held_remove(path: str | Path, *args: Any, **kwargs: Any) -> None:
        if Path(path).parent == incoming:
            gate.hold()
        remove(path, *args, **kwargs)

    monkeypatch.setattr(ingest.shutil, "rmtree", held_remove)
    limit = len(body) // 2

    sent, bindings, answered_while_removing = upload_while_held(
        node, body, gate, StorageSettings(storage_max_bag_bytes=limit)
    )

    assert answered_while_removing
    assert bindings.json() == node.bindings.to_json()
    assert sent.status_code == 413, sent.text
    assert sent.json() == {"code": "payload_too_large", "limit": limit}
    assert list(incoming.iterdir()) == []
    assert [path.name for path in incoming.parent.iterdir() if path.is_dir()] == ["incoming"]


def test_the_knowledge_base_s_state_is_read_off_the_event_loop(
    records_app: FastAPI, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The knowledge base's lock is held across the fsyncs of each description stored (by
    robots, the ledger follower, the dataset publisher), and ``GET /v1/knowledge`` took it
    on the event loop."""
    settings = StorageSettings(data_dir=tmp_path / "node")
    records_app.include_router(knowledge_api.knowledge_router(settings))
    knowledge = records_app.state.knowledge = knowledge_api.open_knowledge(settings)
    gate = Gate()
    monkeypatch.setattr(knowledge, "follow_state", gate.wrap(knowledge.follow_state))
    try:
        state, bindings = held_then_probed(
            records_app, gate, ("GET", "/v1/knowledge"), ("GET", "/v1/bindings")
        )
    finally:
        knowledge.close()

    assert state.status_code == 200, state.text
    assert (state.json()["descriptions"], state.json()["bytes"]) == (0, 0)
    assert bindings.json() == {"topics": {}, "msgtypes": {}}
