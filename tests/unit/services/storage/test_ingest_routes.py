"""The ingest routes while the ingest thread writes a job to disk: nothing waits for it."""

from __future__ import annotations

import asyncio
import hashlib
import threading
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path

import httpx
import pytest
from fastapi import FastAPI
from starlette.types import ASGIApp, Receive, Scope, Send

from robocloud.signing import VerifiedRequest
from services.storage import bags_api, ingest
from tests.unit.services.storage.test_ingest import Node, authorship, bag

SAVE_HELD_S = 10.0


@pytest.fixture
def node(tmp_path: Path) -> Iterator[Node]:
    created = Node(tmp_path / "node")
    yield created
    created.close()


def signed_by(app: ASGIApp, verified: VerifiedRequest) -> ASGIApp:
    """``app`` with every request's signature taken as verified (the guard's part)."""

    async def signed(scope: Scope, receive: Receive, send: Send) -> None:
        scope.setdefault("state", {})["signature"] = verified
        await app(scope, receive, send)

    return signed


def test_polls_and_resends_answer_while_a_job_is_saved(
    node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The ingest thread saves job.json (two fsyncs) at each step, a batch of records each
    while committing, and held the jobs' lock meanwhile; ``GET /v1/jobs/{id}`` and a
    resend's check for the robot's unfinished job took that lock on the event loop, so
    a slow disk stopped every route of the service, and polls waited for the disk. Here a
    save is held until the requests sent during it answered (or 10 s passed): they answer
    from memory, the job as it is, and the service's other routes with them."""
    imu = node.approve("sensor_msgs/msg/Imu")
    node.bindings.bind(template_id=imu, msgtype="sensor_msgs/msg/Imu")
    saving, saved, gave_up = threading.Event(), threading.Event(), threading.Event()
    write = ingest.atomic_write

    def held_write(path: Path, data: bytes) -> None:
        if b'"status": "staging"' in data and not saving.is_set():
            saving.set()
            if not saved.wait(SAVE_HELD_S):
                gave_up.set()
        write(path, data)

    monkeypatch.setattr(ingest, "atomic_write", held_write)
    upload = bag(tmp_path, "b.bag", 200, "ros1")
    body = upload.read_bytes()
    digest = hashlib.sha256(body).hexdigest()
    robot = authorship()
    job = node.jobs.submit(upload, f"upload:{digest}", robot)
    assert saving.wait(SAVE_HELD_S)

    app = FastAPI()
    app.include_router(bags_api.router)
    app.state.ingest_jobs = node.jobs
    app.state.bindings = node.bindings
    verified = VerifiedRequest(robot.signer, 1, "n" * 16, digest, "storage@local")
    answered_while_saving: dict[str, bool] = {}

    async def during_save(name: str, request: Awaitable[httpx.Response]) -> httpx.Response:
        response = await request
        answered_while_saving[name] = not (saved.is_set() or gave_up.is_set())
        return response

    async def requests() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=signed_by(app, verified))
        async with httpx.AsyncClient(transport=transport, base_url="http://storage") as client:
            send: dict[str, Callable[[], Awaitable[httpx.Response]]] = {
                "poll": lambda: client.get(f"/v1/jobs/{job.id}"),
                "resend": lambda: client.post(
                    "/v1/ingest",
                    content=body,
                    headers={"Content-Type": "application/octet-stream"},
                ),
                "bindings": lambda: client.get("/v1/bindings"),
            }
            try:
                return await asyncio.gather(*(during_save(k, v()) for k, v in send.items()))
            finally:
                saved.set()

    poll, resend, bindings = asyncio.run(requests())

    assert answered_while_saving == {"poll": True, "resend": True, "bindings": True}
    assert poll.status_code == 200, poll.text
    assert (poll.json()["id"], poll.json()["status"]) == (job.id, "staging")
    assert resend.status_code == 202, resend.text
    assert (resend.json()["id"], resend.headers["location"]) == (job.id, f"/v1/jobs/{job.id}")
    assert bindings.json() == node.bindings.to_json()
    finished = node.jobs.wait(job.id, 60)
    assert (finished.status, finished.records_committed) == ("succeeded", 160), finished.error
    assert [path.parent.name for path in (node.root / "jobs").glob("*/job.json")] == [job.id]
