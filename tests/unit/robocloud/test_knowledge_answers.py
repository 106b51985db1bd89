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
