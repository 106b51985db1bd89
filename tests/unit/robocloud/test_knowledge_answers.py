"""``Knowledge`` against a hostile storage node on a real socket: a SPARQL answer that is not
what was asked for is an ``InvalidAnswerError`` naming it, never a bare exception."""

from __future__ import annotations

import json
from typing import Any

import pytest

from robocloud.errors import InvalidAnswerError
from robocloud.knowledge import SPARQL_JSON, Knowledge
from tests.scripted_http import json_reply, nested_json, scripted_server

QUERY = "SELECT ?s WHERE { ?s ?p ?o }"


@pytest.mark.parametrize(
    "body",
    [
        b"<html>proxy login</html>",
        nested_json(100_000),
        b'{"results": {"bindings": [{"s": {"value": "a"}}]}, "x": 1, "x": 2}',
        b'{"results": {"bindings": [{"s": "a"}]}}',
        b'{"results": []}',
    ],
    ids=["html", "nested", "duplicate-key", "value-not-object", "results-list"],
)
def test_a_select_answer_that_is_not_sparql_json_is_an_invalid_answer(body: bytes) -> None:
    """Not JSON at all (a proxy's page, nesting past the bound) raised the parser's
    JsonError, a wire-format error, where every other malformed answer is invalid."""
    answer = (200, {"Content-Type": SPARQL_JSON}, body)
    with (
        scripted_server(lambda _: answer) as node,
        Knowledge(node.url, retries=0) as knowledge,
        pytest.raises(InvalidAnswerError, match="not SPARQL JSON results"),
    ):
        knowledge.select(QUERY)


@pytest.mark.parametrize(
    "value",
    [5, 1.5, True, None, {"a": 1}, ["a"]],
    ids=["int", "float", "bool", "null", "object", "list"],
)
def test_a_select_value_that_is_not_a_string_is_an_invalid_answer_naming_it(value: Any) -> None:
    """SPARQL 1.1 JSON results bind every value as a string; a number or an object went
    through ``str()`` and reached the robot as text the query never matched (``"5"``,
    ``"{'a': 1}"``, ``"None"``)."""
    row = {"s": {"type": "literal", "value": "a"}, "o": {"type": "literal", "value": value}}
    body = json.dumps({"head": {"vars": ["s", "o"]}, "results": {"bindings": [row]}})
    answer = (200, {"Content-Type": SPARQL_JSON}, body.encode())
    with (
        scripted_server(lambda _: answer) as node,
        Knowledge(node.url, retries=0) as knowledge,
        pytest.raises(InvalidAnswerError, match=r"bound variable 'o' to .*, not a string"),
    ):
        knowledge.select(QUERY)


def test_a_select_answer_gives_each_rows_strings() -> None:
    rows = [{"s": {"type": "uri", "value": "urn:a"}}, {}]
    body = json.dumps({"head": {"vars": ["s"]}, "results": {"bindings": rows}})
    answer = (200, {"Content-Type": SPARQL_JSON}, body.encode())
    with scripted_server(lambda _: answer) as node, Knowledge(node.url, retries=0) as knowledge:
        assert knowledge.select(QUERY) == [{"s": "urn:a"}, {}]


@pytest.mark.parametrize(
    "answer",
    [{"applications": [1, "two"]}, {"applications": {"a": {}}}, [{"applications": []}]],
    ids=["items-not-objects", "object", "list"],
)
def test_applications_that_are_not_objects_are_an_invalid_answer(answer: Any) -> None:
    """A list of numbers was handed on as the applications, for the robot's first
    ``application["name"]`` to fail as a bare TypeError."""
    with (
        scripted_server(lambda _: json_reply(json.dumps(answer))) as node,
        Knowledge(node.url, retries=0) as knowledge,
        pytest.raises(InvalidAnswerError, match="not a list of objects"),
    ):
        knowledge.applications("image/jpeg")
