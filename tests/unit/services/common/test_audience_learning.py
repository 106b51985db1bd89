"""A service learning its deployment id from the ledger says each problem once, not at every
retry: under ``make up`` every service started before the ledger listened and wrote a warning
every few hundred milliseconds until it did."""

from __future__ import annotations

import json
import logging

import anyio
import pytest

from services.common.audience import ServiceAudience, learn_from_ledger
from tests.procs import free_port
from tests.scripted_http import Exchange, Reply, json_reply, scripted_server

REGISTRY = "0x5fbdb2315678afecb367f032d93f642f64180aa3"
SERVED = f"1337:{REGISTRY}"
EXPECTED = f"31337:{REGISTRY}"


def messages(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [record.getMessage() for record in caplog.records if record.name == "robocloud.audience"]


async def learning_for(
    seconds: float, audience: ServiceAudience, url: str, expected: str | None = None
) -> None:
    with anyio.move_on_after(seconds):
        await learn_from_ledger(audience, url, expected=expected, retry_s=0.05, max_retry_s=0.1)


def test_an_unreachable_ledger_is_said_once(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, "robocloud.audience")
    audience = ServiceAudience("cas", source="the ledger")
    anyio.run(learning_for, 1.0, audience, f"http://127.0.0.1:{free_port()}")
    assert messages(caplog) == ["deployment id not learned yet"]
    assert audience.known is None
    assert audience.problem is not None
    assert "did not tell it" in audience.problem


def test_a_ledger_of_another_deployment_is_said_once(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, "robocloud.audience")

    def ledger(exchange: Exchange) -> Reply:
        answer = {"audience": f"ledger@{SERVED}", "service": "ledger", "deployment": SERVED}
        return json_reply(json.dumps(answer))

    audience = ServiceAudience("cas", source="the ledger")
    with scripted_server(ledger, answer_audience=False) as server:
        anyio.run(learning_for, 1.0, audience, server.url, EXPECTED)
    assert messages(caplog) == ["wrong ledger"]
    assert audience.known is None
    assert audience.problem is not None
    assert f"serves deployment {SERVED}" in audience.problem
