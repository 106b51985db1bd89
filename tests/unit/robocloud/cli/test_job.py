"""``robocloud job ID`` against a scripted storage node: a job that ``ingest`` stopped waiting
for, a dataset the node publishes later, and a job failed while committing, run again."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path
from typing import Any

from typer.testing import CliRunner

from robocloud.cli import app
from tests.scripted_http import Exchange, Reply, json_reply, scripted_server

runner = CliRunner()


def job(status: str, **fields: Any) -> dict[str, Any]:
    topic = {"topic": "/imu", "msgtype": "sensor_msgs/msg/Imu", "template": "imu@1"}
    return {
        "id": "j1",
        "status": status,
        "messages": {"done": 160, "total": 160},
        "records": {"staged": 160, "committed": 160 if status == "succeeded" else 50},
        "topics": [{**topic, "skipped": None}],
        "error": None,
        "dataset": None,
        "updated_ns": 1,
        **fields,
    }


def serving(*states: dict[str, Any]) -> Any:
    """A node answering each GET of job j1 with the next of ``states`` (the last one after),
    a resume with the first, and any other job with 404."""
    answers = list(states)

    def script(exchange: Exchange) -> Reply:
        if exchange.path.split("?")[0] == "/v1/jobs/j1":
            state = answers.pop(0) if len(answers) > 1 else answers[0]
            return json_reply(json.dumps(state))
        if exchange.path == "/v1/jobs/j1/resume" and exchange.method == "POST":
            return json_reply(json.dumps(job("committing")), 202)
        error = {"code": "job_not_found", "message": "no ingest job 'j2'", "details": {}}
        return json_reply(json.dumps({"error": error}), 404)

    return script


def test_a_dataset_the_node_publishes_later_says_when_it_tries_again() -> None:
    retrying = {
        "error": "cas is out",
        "attempts": 2,
        "next_attempt_ns": time.time_ns() + 600 * 10**9,
    }
    with scripted_server(serving(job("succeeded", dataset=retrying))) as node:
        shown = runner.invoke(app, ["job", "j1", "--storage", node.url])
    assert shown.exit_code == 0, shown.output
    lines = shown.stdout.splitlines()
    assert lines[:2] == ["job j1: succeeded, 160 records", "  /imu (sensor_msgs/msg/Imu): imu@1"]
    said = re.fullmatch(
        r"dataset not published yet: cas is out \(attempt 2; the node tries again in about "
        r"(\d+) s: see robocloud job ID\)",
        lines[2],
    )
    assert said is not None, lines[2]
    assert 590 <= int(said.group(1)) <= 600


def test_a_dataset_given_up_on_says_after_how_many_attempts() -> None:
    given_up = {"error": "cas is out", "attempts": 8}
    with scripted_server(serving(job("succeeded", dataset=given_up))) as node:
        shown = runner.invoke(app, ["job", "j1", "--storage", node.url])
    assert shown.exit_code == 0, shown.output
    assert shown.stdout.splitlines()[-1] == "dataset not published: cas is out (after 8 attempts)"


def test_wait_polls_until_the_job_finishes() -> None:
    states = (job("staging"), job("committing"), job("succeeded"))
    with scripted_server(serving(*states)) as node:
        shown = runner.invoke(app, ["job", "j1", "--wait", "--storage", node.url, "--json"])
        assert node.count("GET") == 3
    assert shown.exit_code == 0, shown.output
    assert json.loads(shown.stdout)["status"] == "succeeded"


def test_a_job_failed_while_committing_is_shown_with_how_to_run_it_again() -> None:
    error = {"code": "ingest_failed", "message": "OSError: disk full", "resumable": True}
    with scripted_server(serving(job("failed", error=error))) as node:
        shown = runner.invoke(app, ["job", "j1", "--storage", node.url])
    assert shown.exit_code == 1
    assert shown.stdout.startswith("job j1: failed, 50 records\n")
    assert shown.stderr == (
        "error: ingest failed: OSError: disk full "
        "(hint: run it again with robocloud job j1 --resume)\n"
    )


def test_a_resumable_job_says_until_when_it_can_be_resumed() -> None:
    error = {
        "code": "ingest_failed",
        "message": "OSError: disk full",
        "resumable": True,
        "resumable_until_ns": 1_796_169_600_000_000_000,
    }
    with scripted_server(serving(job("failed", error=error))) as node:
        shown = runner.invoke(app, ["job", "j1", "--storage", node.url])
    assert shown.exit_code == 1
    assert shown.stderr == (
        "error: ingest failed: OSError: disk full (hint: run it again with robocloud job j1 "
        "--resume before 2026-12-02 00:00 UTC, or after that send the bag again)\n"
    )


def test_resume_posts_a_signed_resume_and_waits_for_the_job(keystore: Path) -> None:
    states = (job("committing"), job("succeeded"))
    with scripted_server(serving(*states)) as node:
        shown = runner.invoke(
            app, ["job", "j1", "--resume", "--storage", node.url, "--keystore", str(keystore)]
        )
        posts = [e for e in node.exchanges if e.method == "POST"]
    assert shown.exit_code == 0, shown.output
    assert [post.path for post in posts] == ["/v1/jobs/j1/resume"]
    assert "x-robocloud-signature" in {name.lower() for name in posts[0].headers}
    assert shown.stdout.splitlines()[0] == "job j1: succeeded, 160 records"


def test_an_unknown_job_is_refused_naming_it() -> None:
    with scripted_server(serving(job("succeeded"))) as node:
        shown = runner.invoke(app, ["job", "j2", "--storage", node.url])
    assert shown.exit_code == 4
    assert shown.stdout == ""
    assert "no ingest job 'j2'" in shown.stderr
