"""``LedgerService.robot`` and ``pending`` against a scripted ledger: what a registrar and the
services' registry check believe, so a lying or broken answer is refused, never shown."""

from __future__ import annotations

import json
from typing import Any

import pytest

from robocloud.errors import InvalidAnswerError
from robocloud.ledger import LedgerService
from tests.scripted_http import Exchange, Reply, json_reply, scripted_server

ROBOT = "0x5B38Da6a701c568545dCfcB03FcB875f56beddC4"
OTHER = "0xAb8483F64d9C6d1EcF9b849Ae677dD3315835cb2"


def record(address: str = ROBOT, **changes: Any) -> dict[str, Any]:
    """A pending robot as ``GET /v1/robots/{address}`` answers it."""
    body: dict[str, Any] = {
        "address": address,
        "did": f"did:pkh:eip155:1337:{address}",
        "status": "pending",
        "metadata": {"cid": None, "hex": "0x0170"},
        "registered_at": 1_700_000_000,
        "registered_block": 7,
        "active": False,
        "deactivated": False,
        "suspended": False,
        "roles": [],
    }
    return body | changes


def answering(body: object) -> Any:
    def script(_: Exchange) -> Reply:
        return json_reply(json.dumps(body))

    return script


def test_pending_registrations_are_read_in_order() -> None:
    listed = [record(ROBOT), record(OTHER, registered_block=9)]
    with (
        scripted_server(answering({"pending": listed})) as ledger,
        LedgerService(ledger.url) as service,
    ):
        waiting = service.pending(limit=2)
    assert [(robot.address, robot.pending) for robot in waiting] == [(ROBOT, True), (OTHER, True)]
    assert ledger.exchanges[0].path == "/v1/registrations?limit=2"


@pytest.mark.parametrize(
    ("body", "complaint"),
    [
        ([], "not a list"),
        ({"pending": {"0": record()}}, "not a list"),
        ({"pending": [record(), record(OTHER)]}, "more than the 1 asked for"),
        ({"pending": [record(status="registered")]}, "with status 'registered'"),
        ({"pending": [record(status="admitted")]}, "status must be registered or pending"),
        ({"pending": [record(active=True)]}, "neither active nor hold roles"),
        ({"pending": [record(roles=["registrar"])]}, "neither active nor hold roles"),
        ({"pending": [record(address="0x12")]}, "not an Ethereum address"),
        ({"pending": [record(registered_at="soon")]}, "registered_at has the wrong type"),
        ({"pending": [{"address": ROBOT}]}, "metadata object"),
    ],
    ids=[
        "not-an-object",
        "not-a-list",
        "beyond-the-limit",
        "not-pending",
        "unknown-status",
        "pending-yet-active",
        "pending-with-roles",
        "bad-address",
        "bad-time",
        "no-metadata",
    ],
)
def test_a_malformed_pending_list_is_refused(body: object, complaint: str) -> None:
    with (
        scripted_server(answering(body)) as ledger,
        LedgerService(ledger.url) as service,
        pytest.raises(InvalidAnswerError) as refused,
    ):
        service.pending(limit=1)
    assert complaint in str(refused.value)


def test_a_record_of_another_robot_is_refused() -> None:
    """The services admit writers by this answer: one about someone else admits no one."""
    with (
        scripted_server(answering(record(OTHER, status="registered", active=True))) as ledger,
        LedgerService(ledger.url) as service,
        pytest.raises(InvalidAnswerError) as refused,
    ):
        service.robot(ROBOT)
    assert f"asked for the record of {ROBOT}" in str(refused.value)
    assert ledger.exchanges[0].path == f"/v1/robots/{ROBOT}"


def test_a_pending_record_is_read_as_pending() -> None:
    with scripted_server(answering(record())) as ledger, LedgerService(ledger.url) as service:
        found = service.robot(ROBOT.lower())
    assert found is not None
    assert (found.address, found.pending, found.active) == (ROBOT, True, False)
