"""What a service said reaches the terminal escaped (docs/cli.md, "Untrusted text"): a hostile
storage node cannot recolour the terminal, erase a line or forge one such as
``record imu-1-0 verified`` with escape sequences and newlines in its answers."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner, Result

from robocloud.cli import app
from tests.scripted_http import Exchange, Reply, Script, json_reply, scripted_server

EVIL = "ok\x1b[2K\r\x1b[31mFORGED\x1b[0m\nrecord   imu-1-0 verified\u202e"
ESCAPED = "ok\\x1b[2K\\r\\x1b[31mFORGED\\x1b[0m\\nrecord   imu-1-0 verified\\u202e"
runner = CliRunner()


def template(**fields: Any) -> dict[str, Any]:
    document = {"name": "imu", "version": 1, "fields": {"x": "int"}, "description": "d"}
    return {**document, "status": EVIL, "author": EVIL, "reviewer": EVIL, **fields}


def storage_node(exchange: Exchange) -> Reply:
    """A storage node whose every free-text field says ``EVIL``."""
    if exchange.path.startswith("/v1/templates?"):
        return json_reply(json.dumps({"templates": [template()], "next": None}))
    if exchange.path.startswith("/v1/templates/"):
        return json_reply(json.dumps(template()))
    if exchange.path.startswith("/v1/intervals"):
        interval = {"robot": EVIL, "enter": 1, "exit": None}
        return json_reply(json.dumps({"template": "imu@1", "intervals": [interval]}))
    if exchange.path.startswith("/v1/records"):
        record = {"template": "imu@1", "topic": EVIL, "robot": "0x", "t": EVIL, "data": {}}
        return json_reply(json.dumps({"records": [{"id": EVIL, "record": record}], "next": EVIL}))
    if exchange.path in ("/v1/ingest",) or exchange.path.startswith("/v1/jobs/"):
        topic = {"topic": EVIL, "msgtype": EVIL, "template": EVIL, "skipped": None}
        job = {
            "id": "j1",
            "status": "succeeded",
            "messages": {"done": 1, "total": 1},
            "records": {"staged": 1, "committed": 1},
            "topics": [topic],
            "error": None,
            "updated_ns": 1,
        }
        return json_reply(json.dumps(job))
    return json_reply(b'{"error":{"code":"not_found","message":"no"}}', 404)


def assert_escaped(stdout: str, lines: int) -> None:
    assert "\x1b" not in stdout
    assert "\u202e" not in stdout
    assert "\r" not in stdout
    assert stdout.count("\n") == lines
    assert ESCAPED[:40] in stdout


@pytest.mark.parametrize(
    ("command", "lines"),
    [
        (["templates", "list"], 1),
        (["templates", "show", "imu@1"], 7),
        (["query"], 3),
        (["intervals", "--template", "imu@1", "--field", "x", "--value", "1"], 2),
    ],
    ids=["templates-list", "templates-show", "query", "intervals"],
)
def test_storage_answers_are_printed_escaped(command: list[str], lines: int) -> None:
    with scripted_server(storage_node) as server:
        result = runner.invoke(app, [*command, "--storage", server.url])
    assert result.exit_code == 0, result.output
    assert_escaped(result.stdout, lines)


def ingest_report(node: Script, keystore: Path, tmp_path: Path) -> Result:
    """``robocloud ingest`` of a small MCAP file against the storage node ``node``."""
    bag = tmp_path / "x.mcap"
    bag.write_bytes(b"\x89MCAP0\r\n" + bytes(64))
    with scripted_server(node) as server:
        return runner.invoke(
            app, ["ingest", str(bag), "--storage", server.url, "--keystore", str(keystore)]
        )


def test_an_ingest_report_is_printed_escaped(keystore: Path, tmp_path: Path) -> None:
    result = ingest_report(storage_node, keystore, tmp_path)
    assert result.exit_code == 0, result.output
    assert_escaped(result.stdout, 2)
    assert result.stdout.startswith("job j1: succeeded, 1 records\n")


@pytest.mark.parametrize(
    ("dataset", "said"),
    [
        ({"error": EVIL}, f"dataset not published: {ESCAPED}"),
        (
            {"cid": "bafy-bag", "description": "bafk-description", "tx": EVIL},
            f"dataset bafy-bag, described by bafk-description, advertised in {ESCAPED}",
        ),
    ],
    ids=["not-published", "published"],
)
def test_an_ingest_report_says_what_became_of_the_dataset(
    keystore: Path, tmp_path: Path, dataset: dict[str, str], said: str
) -> None:
    """A dataset that failed to publish was said only in the storage node's log."""

    def node(exchange: Exchange) -> Reply:
        status, headers, body = storage_node(exchange) or (500, {}, b"")
        if exchange.path.startswith("/v1/jobs/"):
            body = json.dumps({**json.loads(body), "dataset": dataset}).encode()
        return status, headers, body

    result = ingest_report(node, keystore, tmp_path)
    assert result.exit_code == 0, result.output
    assert_escaped(result.stdout, 3)
    assert result.stdout.splitlines()[-1] == said


def test_an_ingest_report_says_which_job_ingested_a_skipped_topic(
    keystore: Path, tmp_path: Path
) -> None:
    """A topic skipped as ingested from the bag before keeps its template: the line showed
    the template alone, as though the topic had been ingested again."""
    skipped = "ingested from this bag into imu@1 by job j0"

    def node(exchange: Exchange) -> Reply:
        status, headers, body = storage_node(exchange) or (500, {}, b"")
        if exchange.path.startswith("/v1/jobs/"):
            topic = {"topic": "/imu", "msgtype": "sensor_msgs/msg/Imu", "template": "imu@1"}
            topic |= {"skipped": skipped, "ingested_by": "j0"}
            body = json.dumps({**json.loads(body), "topics": [topic]}).encode()
        return status, headers, body

    result = ingest_report(node, keystore, tmp_path)
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines()[1] == f"  /imu (sensor_msgs/msg/Imu): {skipped}"


def sparql_node(body: bytes, media_type: str) -> Any:
    def script(_: Exchange) -> Reply:
        return 200, {"Content-Type": media_type}, body

    return script


def test_sparql_column_names_and_values_are_printed_escaped() -> None:
    results = {"head": {"vars": [EVIL]}, "results": {"bindings": [{EVIL: {"value": EVIL}}]}}
    answer = sparql_node(json.dumps(results).encode(), "application/sparql-results+json")
    with scripted_server(answer) as server:
        result = runner.invoke(app, ["sparql", "SELECT * {?s ?p ?o}", "--storage", server.url])
    assert result.exit_code == 0, result.output
    assert_escaped(result.stdout, 2)
    assert result.stdout == f"{ESCAPED}\n{ESCAPED}\n"


def test_a_construct_answer_is_printed_escaped_line_by_line() -> None:
    turtle = f'<urn:a> <urn:b> "{EVIL}" .\n'.encode()
    with scripted_server(sparql_node(turtle, "text/turtle")) as server:
        result = runner.invoke(app, ["sparql", "CONSTRUCT {?s ?p ?o} {}", "--storage", server.url])
    assert result.exit_code == 0, result.output
    assert "\x1b" not in result.stdout
    assert "\u202e" not in result.stdout
    assert "\r" not in result.stdout
    assert '<urn:a> <urn:b> "ok\\x1b[2K\n' in result.stdout


C1_EVIL = "\x9b2J\x9b31mFORGED\u2028record   imu-1-0 verified\u202e\U000e0001"


@pytest.mark.parametrize(
    "command",
    [["templates", "list"], ["templates", "show", "imu@1"], ["query"]],
    ids=["templates-list", "templates-show", "query"],
)
def test_json_output_escapes_what_json_itself_leaves_raw(command: list[str]) -> None:
    """JSON escapes only characters below U+0020: a C1 CSI (U+009B, a terminal's ESC [), a
    line separator, a bidi override or a tag character in a service's text reached the
    terminal raw under --json. Escaped as \\uXXXX, the document still reads the same."""
    evil_node = _saying(C1_EVIL)
    with scripted_server(evil_node) as server:
        result = runner.invoke(app, [*command, "--storage", server.url, "--json"])
    assert result.exit_code == 0, result.output
    assert result.stdout.isascii()
    assert C1_EVIL in json.dumps(json.loads(result.stdout), ensure_ascii=False)


def _saying(text: str) -> Any:
    """``storage_node`` with ``text`` wherever it says ``EVIL``."""

    def script(exchange: Exchange) -> Reply:
        status, headers, body = storage_node(exchange) or (500, {}, b"")
        return (
            status,
            headers,
            body.replace(json.dumps(EVIL)[1:-1].encode(), json.dumps(text)[1:-1].encode()),
        )

    return script
