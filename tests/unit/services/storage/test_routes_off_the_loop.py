"""Storage routes whose slow part (a disk write, a parse) is held: the service's other routes
answer meanwhile, as they do only when that part runs off the event loop."""

from __future__ import annotations

import asyncio
import hashlib
import json
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi import FastAPI

from robocloud import bounded_json
from robocloud.signing import VerifiedRequest
from services.common.bodies import INLINE_JSON_BYTES
from services.storage import bags_api, ingest, records_api
from services.storage.matcher import Bindings
from services.storage.settings import StorageSettings
from tests.held import Gate, answered_while_held, probed, signed_by
from tests.unit.services.storage.conftest import ROBOT_A, StoreFactory, state_record
from tests.unit.services.storage.test_ingest import Node, authorship, bag


@pytest.fixture
def node(tmp_path: Path) -> Iterator[Node]:
    created = Node(tmp_path / "node")
    yield created
    created.close()


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


def test_a_large_batch_of_records_is_parsed_off_the_event_loop(
    open_store: StoreFactory, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A JSON array of records (64 MiB at most) was parsed on the event loop, about 3 s
    for the largest, every route of the service waiting; it is parsed on a thread now."""
    store = open_store()
    app = FastAPI()
    app.include_router(records_api.router)
    app.include_router(bags_api.router)
    app.state.settings = StorageSettings()
    app.state.records = store
    app.state.catalog = store.catalog
    app.state.bindings = Bindings(tmp_path / "bindings.json")
    gate = Gate()
    monkeypatch.setattr(bounded_json, "loads", gate.wrap(bounded_json.loads))
    batch = [state_record(t) for t in range(1000)]
    body = json.dumps(batch).encode()
    assert len(body) > INLINE_JSON_BYTES

    async def requests() -> tuple[httpx.Response, dict[str, httpx.Response], dict[str, bool]]:
        verified = VerifiedRequest(ROBOT_A, 1, "n" * 16, hashlib.sha256(body).hexdigest(), "s")
        async with in_process(app, verified) as client:
            held = client.post(
                "/v1/records", content=body, headers={"Content-Type": "application/json"}
            )
            return await answered_while_held(
                gate, held, {"bindings": lambda: client.get("/v1/bindings")}
            )

    stored, answers, answered_while_parsing = asyncio.run(requests())

    assert answered_while_parsing == {"bindings": True}
    assert answers["bindings"].json() == {"topics": {}, "msgtypes": {}}
    assert stored.status_code == 201, stored.text
    assert stored.json()["count"] == 1000
    assert store.logs.size("state@1") == 1000


def test_an_upload_is_hashed_and_written_off_the_event_loop(
    node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A bag upload (16 GiB at most) was hashed and written chunk by chunk on the event
    loop: a write the kernel throttled held every route. Its one batch is held here."""
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    body = bag(tmp_path, "b.bag", 200, "ros1").read_bytes()
    digest = hashlib.sha256(body).hexdigest()
    gate = Gate()
    monkeypatch.setattr(bags_api, "_spooled", gate.wrap(bags_api._spooled))
    app = FastAPI()
    app.include_router(bags_api.router)
    app.state.settings = StorageSettings()
    app.state.ingest_jobs = node.jobs
    app.state.bindings = node.bindings
    robot = authorship()

    async def requests() -> tuple[httpx.Response, dict[str, httpx.Response], dict[str, bool]]:
        verified = VerifiedRequest(robot.signer, 1, "n" * 16, digest, "storage@local")
        async with in_process(app, verified) as client:
            held = client.post(
                "/v1/ingest", content=body, headers={"Content-Type": "application/octet-stream"}
            )
            return await answered_while_held(
                gate, held, {"bindings": lambda: client.get("/v1/bindings")}
            )

    sent, answers, answered_while_writing = asyncio.run(requests())

    assert answered_while_writing == {"bindings": True}
    assert answers["bindings"].json() == node.bindings.to_json()
    assert sent.status_code == 202, sent.text
    assert sent.json()["bag"] == f"upload:{digest}"
    finished = node.jobs.wait(sent.json()["id"], 120)
    assert (finished.status, finished.records_committed) == ("succeeded", 160), finished.error
