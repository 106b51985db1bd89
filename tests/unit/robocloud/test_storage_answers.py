"""``Storage`` against a hostile storage node on a real socket: intervals are taken as the
service builds them (``Interval.to_json``), and anything else is an invalid answer, never a
coerced time the robot would then believe."""

from __future__ import annotations

import json
from typing import Any

import pytest

from robocloud.errors import InvalidAnswerError
from robocloud.identity import Identity
from robocloud.storage import Interval, Storage
from tests.scripted_http import Exchange, Reply, json_reply, scripted_server

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
