"""``Ingest`` against a hostile storage node on a real socket: what it answers is parsed
within the SDK's bounds, never trusted for its shape.

This test process has py_ecc's raised recursion limit, so an answer parsed without the
nesting bound would overflow the C stack and kill it rather than fail a test.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from robocloud.bounded_json import JsonDepthError
from robocloud.cli import app
from robocloud.errors import InvalidAnswerError
from robocloud.identity import Identity
from robocloud.ingest import ExportTooLargeError, Ingest
from tests.scripted_http import Exchange, Reply, json_reply, nested_json, scripted_server
from tests.unit.robocloud.test_cas_answers import ENDLESS_CAP, endless_server

runner = CliRunner()


@pytest.fixture
def bag(tmp_path: Path) -> Path:
    path = tmp_path / "x.mcap"
    path.write_bytes(b"\x89MCAP0\r\n" + bytes(64))
    return path


def test_an_upload_answer_nested_past_the_bound_is_an_invalid_answer(bag: Path) -> None:
    def script(_: Exchange) -> Reply:
        return json_reply(nested_json(100_000))

    with (
        scripted_server(script) as server,
        Ingest(server.url, Identity.generate(), retries=0) as ingest,
        pytest.raises(InvalidAnswerError) as err,
    ):
        ingest.upload(bag)
    assert isinstance(err.value.__cause__, JsonDepthError)
    assert "POST /v1/ingest" in str(err.value)


def test_an_upload_answer_that_is_not_json_is_an_invalid_answer(bag: Path) -> None:
    page = (200, {"Content-Type": "text/html"}, b"<html>proxy login</html>")
    with (
        scripted_server(lambda _: page) as server,
        Ingest(server.url, Identity.generate(), retries=0) as ingest,
        pytest.raises(InvalidAnswerError, match="not usable JSON"),
    ):
        ingest.upload(bag)


JOB: dict[str, Any] = {
    "id": "j1",
    "status": "succeeded",
    "messages": {"done": 1, "total": 1},
    "records": {"staged": 1, "committed": 1},
    "topics": [],
    "error": None,
    "updated_ns": 1,
}


@pytest.mark.parametrize(
    "job",
    [
        {key: value for key, value in JOB.items() if key != "status"},
        {key: value for key, value in JOB.items() if key != "messages"},
        {**JOB, "records": {"committed": "1"}},
        {**JOB, "topics": "none"},
        {**JOB, "status": "failed"},
        {**JOB, "id": 7},
        {**JOB, "updated_ns": "1"},
        [JOB],
    ],
    ids=[
        "no-status",
        "no-messages",
        "count-text",
        "topics-text",
        "failed-no-error",
        "id",
        "updated-text",
        "list",
    ],
)
def test_a_malformed_job_is_an_invalid_answer(job: Any) -> None:
    with (
        scripted_server(lambda _: json_reply(json.dumps(job))) as server,
        Ingest(server.url) as ingest,
        pytest.raises(InvalidAnswerError, match="malformed ingest job"),
    ):
        ingest.job("j1")


def test_a_job_answered_for_another_id_is_refused() -> None:
    """Waiting for a failing job j1, a node answering another's success had the robot report
    j1 as succeeded."""
    with (
        scripted_server(lambda _: json_reply(json.dumps({**JOB, "id": "j2"}))) as server,
        Ingest(server.url, retries=0) as ingest,
        pytest.raises(InvalidAnswerError, match="ingest job 'j1', the storage service sent 'j2'"),
    ):
        ingest.wait("j1")


@pytest.mark.parametrize("answer", [b"[1]", b'"bound"', b""], ids=["list", "text", "empty"])
def test_a_binding_that_is_not_an_object_is_an_invalid_answer(answer: bytes) -> None:
    """Typed a dict, a list or nothing at all went through to the robot."""
    with (
        scripted_server(lambda _: json_reply(answer)) as server,
        Ingest(server.url, Identity.generate(), retries=0) as ingest,
        pytest.raises(InvalidAnswerError, match="not an object"),
    ):
        ingest.bind("imu@1", topic="/imu")


def test_waiting_asks_for_the_jobs_next_change_and_paces_a_node_that_answers_at_once() -> None:
    """Each read after the first is a long poll past the job's ``updated_ns``; a node that
    does not wait (an older one) is still asked at most every ``poll_s``."""
    queued = {**JOB, "status": "queued", "updated_ns": 7}
    with (
        scripted_server(lambda _: json_reply(json.dumps(queued))) as server,
        Ingest(server.url, retries=0) as ingest,
    ):
        started = time.monotonic()
        last = ingest.wait("j1", poll_s=0.2, timeout_s=1.0)
        took = time.monotonic() - started
    assert last["status"] == "queued"
    paths = [exchange.path for exchange in server.exchanges]
    assert paths[0] == "/v1/jobs/j1"
    assert all(path.startswith("/v1/jobs/j1?after_ns=7&wait_s=") for path in paths[1:])
    assert float(paths[1].rsplit("=", 1)[1]) <= 1.0
    assert 3 <= len(paths) <= 1 + took / 0.2 + 1


@pytest.mark.parametrize("wait_s", [-1, 25.5])
def test_a_wait_past_the_bound_is_refused_before_asking(wait_s: float) -> None:
    with (
        scripted_server(lambda _: json_reply(json.dumps(JOB))) as server,
        Ingest(server.url) as ingest,
        pytest.raises(ValueError, match="wait_s must be between 0 and 25 s"),
    ):
        ingest.job("j1", after_ns=1, wait_s=wait_s)
    assert server.exchanges == []


def test_a_job_id_is_one_path_segment() -> None:
    job = {**JOB, "id": "../templates?x=1"}
    with (
        scripted_server(lambda _: json_reply(json.dumps(job))) as server,
        Ingest(server.url) as ingest,
    ):
        ingest.job("../templates?x=1")
    assert [exchange.path for exchange in server.exchanges] == ["/v1/jobs/..%2Ftemplates%3Fx%3D1"]


def test_ingest_ends_in_one_line_on_a_job_without_status(bag: Path, keystore: Path) -> None:
    job = {key: value for key, value in JOB.items() if key != "status"}
    with scripted_server(lambda _: json_reply(json.dumps(job))) as server:
        result = runner.invoke(
            app, ["ingest", str(bag), "--storage", server.url, "--keystore", str(keystore)]
        )
    assert result.exit_code == 6, result.output
    assert result.stdout == ""
    assert result.stderr.startswith("error: the storage service sent a malformed ingest job")
    assert result.stderr.count("\n") == 1


@pytest.mark.parametrize("max_size", [1 << 20, None], ids=["max-size", "free-space"])
def test_an_export_that_never_ends_is_cut_at_its_bound(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, max_size: int | None
) -> None:
    """An export declares no size: a node streaming one without end filled the disk."""
    free = shutil.disk_usage(tmp_path)._replace(free=1 << 20)
    monkeypatch.setattr("robocloud.partial.shutil.disk_usage", lambda _: free)
    out = tmp_path / "imu.jsonl"
    out.write_bytes(b"the previous export\n")
    with (
        endless_server(b"") as node,
        Ingest(node.url, retries=0) as ingest,
        pytest.raises(ExportTooLargeError, match=f"limit of {1 << 20} bytes"),
    ):
        ingest.export({"template": "imu@1", "format": "jsonl"}, out, max_size=max_size)
    assert node.sent < ENDLESS_CAP // 4
    assert sorted(tmp_path.iterdir()) == [out]
    assert out.read_bytes() == b"the previous export\n"
