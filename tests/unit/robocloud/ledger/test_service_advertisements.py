"""``LedgerService.advertisements`` against a scripted ledger: what the knowledge base's
follower believes, so an answer that would make it skip or misread advertisements is refused."""

from __future__ import annotations

import json
from typing import Any

import pytest

from robocloud.errors import InvalidAnswerError
from robocloud.ledger import IndexedAdvertisement, LedgerService
from tests.scripted_http import Exchange, Reply, json_reply, scripted_server

ROBOT = "0x5B38Da6a701c568545dCfcB03FcB875f56beddC4"
DATA = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"
DESCRIPTION = "bafkreifhyd2reqnaxb6vmuv3gwnyum4osowzkclmxa2qdsj3fhkderxyem"


def event(block: int = 5, log_index: int = 0, **changes: Any) -> dict[str, Any]:
    """One advertisement as ``GET /v1/advertisements`` lists it."""
    body: dict[str, Any] = {
        "cid": DATA,
        "hex": "0x01",
        "advertiser": ROBOT.lower(),
        "description": {"cid": DESCRIPTION, "hex": "0x01"},
        "first": True,
        "timestamp": 1_700_000_000,
        "block_number": block,
        "log_index": log_index,
        "tx": "0x" + "ab" * 32,
    }
    return body | changes


def listing(events: list[Any], seen: list[str]) -> Any:
    def script(exchange: Exchange) -> Reply:
        seen.append(exchange.path)
        return json_reply(json.dumps({"advertisements": events}))

    return script


def test_advertisements_are_read_with_their_description_and_place() -> None:
    seen: list[str] = []
    events = [event(5, 0), event(5, 1, description=None), event(9, 0, cid=None)]
    with scripted_server(listing(events, seen)) as server, LedgerService(server.url) as ledger:
        found = ledger.advertisements(since=5, limit=3, advertiser=ROBOT.lower())
    assert seen == [f"/v1/advertisements?since=5&limit=3&advertiser={ROBOT}"]
    assert found == [
        IndexedAdvertisement(DATA, ROBOT, DESCRIPTION, True, 1_700_000_000, 5, 0, "0x" + "ab" * 32),
        IndexedAdvertisement(DATA, ROBOT, None, True, 1_700_000_000, 5, 1, "0x" + "ab" * 32),
        IndexedAdvertisement(None, ROBOT, DESCRIPTION, True, 1_700_000_000, 9, 0, "0x" + "ab" * 32),
    ]


@pytest.mark.parametrize(
    ("events", "message"),
    [
        ([event(), event(), event()], "3 advertisements, more than the 2 asked for"),
        ([event(6), event(5)], "out of order"),
        ([event(3)], "out of order"),
        ([event(description={"cid": "not-a-cid"})], "malformed"),
        ([event(advertiser="robot")], "malformed"),
        ([event(block_number=-1)], "malformed"),
        ([event(log_index=True)], "malformed"),
        ([event(first="yes")], "malformed"),
        ([{"cid": DATA}], "malformed"),
        (["x"], "malformed"),
    ],
)
def test_a_lying_or_broken_listing_is_refused(events: list[Any], message: str) -> None:
    with (
        scripted_server(listing(events, [])) as server,
        LedgerService(server.url) as ledger,
        pytest.raises(InvalidAnswerError, match=message),
    ):
        ledger.advertisements(since=4, limit=2)


def test_a_position_is_sent_and_an_event_at_or_before_it_is_refused() -> None:
    """A follower saves the last event it read; an event at or before it, sent again, would
    be read twice, or, from a lying ledger, make the follower believe it is past others."""
    seen: list[str] = []
    with (
        scripted_server(listing([event(5, 3), event(6, 0)], seen)) as server,
        LedgerService(server.url) as ledger,
    ):
        found = ledger.advertisements(since=5, after_log_index=2, limit=2)
        assert [(ad.block_number, ad.log_index) for ad in found] == [(5, 3), (6, 0)]
        with pytest.raises(InvalidAnswerError, match="out of order"):
            ledger.advertisements(since=5, after_log_index=3, limit=2)
    assert seen[0] == "/v1/advertisements?since=5&limit=2&after_log_index=2"


@pytest.mark.parametrize("body", [[], {"advertisements": "x"}, {"other": []}])
def test_an_answer_that_is_not_a_listing_is_refused(body: Any) -> None:
    with (
        scripted_server(lambda _: json_reply(json.dumps(body))) as server,
        LedgerService(server.url) as ledger,
        pytest.raises(InvalidAnswerError, match="not a list"),
    ):
        ledger.advertisements()
