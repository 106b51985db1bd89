"""``Ingest`` against a hostile storage node on a real socket: what it answers is parsed
within the SDK's bounds, never trusted for its shape.

This test process has py_ecc's raised recursion limit, so an answer parsed without the
nesting bound would overflow the C stack and kill it rather than fail a test.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from robocloud.bounded_json import JsonDepthError
from robocloud.errors import InvalidAnswerError
from robocloud.identity import Identity
from robocloud.ingest import Ingest
from tests.scripted_http import Exchange, Reply, json_reply, nested_json, scripted_server


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
