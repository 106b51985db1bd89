"""``Storage`` and its commands against a hostile storage node on a real socket.

A catalog that never ends must not grow a robot's memory until it is killed, and what the
service says is neither printed raw on a terminal nor allowed to end a command in a traceback.
Intervals are taken as the service builds them (``Interval.to_json``); anything else is an
invalid answer, never a coerced time the robot would then believe.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any
from urllib.parse import parse_qs, urlsplit

import pytest
from typer.testing import CliRunner

from robocloud.cli import app
from robocloud.errors import InvalidAnswerError
from robocloud.identity import Identity
from robocloud.storage import Interval, Storage
from tests.scripted_http import Exchange, Reply, ScriptedServer, json_reply, scripted_server

runner = CliRunner()


def version(index: int = 1, **fields: Any) -> dict[str, Any]:
    """One template version as the catalog answers it."""
    document = {
        "name": "imu",
        "version": index,
        "fields": {"x": "int"},
        "description": "d",
        "status": "approved",
        "author": "0x" + "ab" * 20,
    }
    return {**document, **fields}


def catalog(
    page: Callable[[str | None, int], tuple[list[dict[str, Any]], Any]],
) -> Callable[[Exchange], Reply]:
    """A storage node whose ``GET /v1/templates`` answers ``page(after, limit)``."""

    def script(exchange: Exchange) -> Reply:
        query = parse_qs(urlsplit(exchange.path).query)
        items, following = page(query.get("after", [None])[0], int(query["limit"][0]))
        return json_reply(json.dumps({"templates": items, "next": following}))

    return script


def listed(server: ScriptedServer, **options: Any) -> list[str]:
    with Storage(server.url) as storage:
        return [item.id for item in storage.templates(**options)]


def test_an_honest_catalog_is_followed_to_its_end() -> None:
    def page(after: str | None, limit: int) -> tuple[list[dict[str, Any]], Any]:
        start = int(after or 0)
        items = [version(index) for index in range(start + 1, min(start + limit, 7) + 1)]
        return items, str(start + limit) if start + limit < 7 else None

    with scripted_server(catalog(page)) as server:
        assert listed(server, limit=3) == [f"imu@{index}" for index in range(1, 8)]
        assert server.count() == 3


def test_a_next_cursor_answered_twice_ends_the_list() -> None:
    with scripted_server(catalog(lambda *_: ([version()] * 10, "again"))) as server:
        with pytest.raises(InvalidAnswerError, match="repeats its page 'again'"):
            listed(server, limit=10)
        assert server.count() == 2


@pytest.mark.parametrize(
    ("items", "following"), [(11, None), (0, "more")], ids=["oversized", "empty-with-next"]
)
def test_a_page_of_another_size_than_asked_is_refused(items: int, following: Any) -> None:
    with (
        scripted_server(catalog(lambda *_: ([version()] * items, following))) as server,
        pytest.raises(InvalidAnswerError, match="asked for pages of 10 template versions"),
    ):
        listed(server, limit=10)


def test_a_catalog_that_invents_pages_forever_is_cut_at_the_bound() -> None:
    def page(after: str | None, limit: int) -> tuple[list[dict[str, Any]], Any]:
        return [version()] * limit, f"{after or ''}x"

    with scripted_server(catalog(page)) as server:
        with pytest.raises(InvalidAnswerError, match="more than 50 template versions"):
            listed(server, limit=10, max_items=50)
        assert server.count() == 6


def test_a_query_page_larger_than_asked_is_refused() -> None:
    record = {"template": "imu@1", "topic": "/imu", "robot": "0x", "t": 1, "data": {}}
    page = {"records": [{"id": f"imu-1-{i}", "record": record} for i in range(3)], "next": None}
    with (
        scripted_server(lambda _: json_reply(json.dumps(page))) as server,
        Storage(server.url) as storage,
        pytest.raises(InvalidAnswerError, match="asked for 2 records"),
    ):
        storage.query(limit=2)


def test_templates_list_ends_in_one_line_on_a_catalog_that_never_ends() -> None:
    with scripted_server(catalog(lambda *_: ([version()] * 100, "again"))) as server:
        result = runner.invoke(app, ["templates", "list", "--storage", server.url])
    assert result.exit_code == 6, result.output
    assert result.stdout == ""
    assert result.stderr.count("\n") == 1


@pytest.mark.parametrize("pending", ["zz", -1, True, 1.5], ids=repr)
def test_a_malformed_keywords_pending_is_an_invalid_answer(pending: Any) -> None:
    page = {"records": [], "next": None, "keywords_pending": pending}
    with (
        scripted_server(lambda _: json_reply(json.dumps(page))) as server,
        Storage(server.url) as storage,
        pytest.raises(InvalidAnswerError, match="keywords_pending"),
    ):
        storage.query()


def test_query_ends_in_one_line_on_a_malformed_page() -> None:
    page = {"records": [], "next": None, "keywords_pending": "zz"}
    with scripted_server(lambda _: json_reply(json.dumps(page))) as server:
        result = runner.invoke(app, ["query", "--storage", server.url])
    assert result.exit_code == 6, result.output
    assert result.stderr.startswith("error: the storage service sent keywords_pending 'zz'")
    assert result.stderr.count("\n") == 1


@pytest.mark.parametrize(
    "call",
    [
        lambda storage: storage.template("imu@2"),
        lambda storage: storage.submit_template("imu@2"),
        lambda storage: storage.review_template("imu@2", "approve"),
        lambda storage: storage.edit_template("imu@2", version(2)),
    ],
    ids=["template", "submit", "review", "edit"],
)
def test_a_template_answered_for_another_id_is_refused(call: Callable[[Storage], Any]) -> None:
    """Asked for imu@2, a node answering imu@1 had the robot validate its records against a
    template it never named."""
    with (
        scripted_server(lambda _: json_reply(json.dumps(version(1)))) as server,
        Storage(server.url, Identity.generate(), retries=0) as storage,
        pytest.raises(InvalidAnswerError, match="template 'imu@2', the storage service sent"),
    ):
        call(storage)


def test_a_record_answered_for_another_id_is_refused() -> None:
    other = {"id": "imu-1-7", "record": {"template": "imu@1", "data": {"x": 1}}, "signer": None}
    with (
        scripted_server(lambda _: json_reply(json.dumps(other))) as server,
        Storage(server.url, retries=0) as storage,
        pytest.raises(InvalidAnswerError, match="record 'imu-1-5', the storage service sent"),
    ):
        storage.record("imu-1-5")


@pytest.mark.parametrize(
    ("call", "answer"),
    [
        (lambda storage: storage.template("imu@1"), version(reviewer=7)),
        (lambda storage: storage.template("imu@1"), version(reason={"a": 1})),
        (
            lambda storage: storage.record("imu-1-5"),
            {"id": "imu-1-5", "record": {"template": "imu@1"}, "signer": ["0x"]},
        ),
    ],
    ids=["reviewer", "reason", "signer"],
)
def test_a_text_field_that_is_not_text_is_an_invalid_answer(
    call: Callable[[Storage], Any], answer: dict[str, Any]
) -> None:
    """Typed ``str | None``, a number or an object went through to fail at the robot's first
    ``.lower()`` as a bare AttributeError."""
    with (
        scripted_server(lambda _: json_reply(json.dumps(answer))) as server,
        Storage(server.url, retries=0) as storage,
        pytest.raises(InvalidAnswerError, match="that is not text"),
    ):
        call(storage)


ROBOT = "0x2c7536E3605D9C16a7a3D7b1898e529396a65c23"


def intervals_answered(items: Any) -> list[Interval]:
    def script(_: Exchange) -> Reply:
        answer = {"template": "state@1", "field": "mode", "value": "x", "intervals": items}
        return json_reply(json.dumps(answer))

    with (
        scripted_server(script) as server,
        Storage(server.url, Identity.generate(), retries=0) as storage,
    ):
        return storage.intervals("state@1", "mode", "x")


def test_intervals_read_back_as_the_service_writes_them() -> None:
    sent = [Interval(ROBOT, 10, 20), Interval(ROBOT, 30, None)]
    assert intervals_answered([interval.to_json() for interval in sent]) == sent


@pytest.mark.parametrize(
    ("item", "named"),
    [
        ({"robot": ROBOT, "enter": "10", "exit": None}, "enter"),
        ({"robot": ROBOT, "enter": True, "exit": None}, "enter"),
        ({"robot": ROBOT, "enter": 10.5, "exit": None}, "enter"),
        ({"robot": ROBOT, "enter": 10, "exit": "20"}, "exit"),
        ({"robot": ROBOT, "enter": 10, "exit": False}, "exit"),
        ({"robot": 7, "enter": 10, "exit": None}, "robot"),
        ({"enter": 10, "exit": None}, "robot"),
        ("10-20", "object"),
    ],
)
def test_an_interval_of_the_wrong_types_is_an_invalid_answer(item: Any, named: str) -> None:
    with pytest.raises(InvalidAnswerError, match=f"invalid intervals: .*{named}"):
        intervals_answered([item])


def test_intervals_that_are_not_a_list_are_an_invalid_answer() -> None:
    with pytest.raises(InvalidAnswerError, match="invalid intervals"):
        intervals_answered(42)
