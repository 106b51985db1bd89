"""``robocloud status``: its latency column is the ``/healthz`` round trip, nothing else."""

from __future__ import annotations

import json
import time

import pytest
from typer.testing import CliRunner

from robocloud.cli import app
from tests.procs import free_port
from tests.scripted_http import Exchange, Reply, json_reply, scripted_server

READY_AFTER_S = 1.0


def slow_to_say_ready(exchange: Exchange) -> Reply:
    if exchange.path == "/readyz":
        time.sleep(READY_AFTER_S)
        return json_reply('{"status": "ready"}')
    return json_reply('{"status": "ok", "service": "cas", "version": "0.1.0"}')


def test_the_latency_is_the_health_probe_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    """It was measured from before the HTTP client was made to after ``/readyz`` answered:
    about 100 ms for a service answering in one or two, and here a second more."""
    down = f"http://127.0.0.1:{free_port()}"
    for name in ("ledger", "storage", "broker", "fl"):
        monkeypatch.setenv(f"ROBOCLOUD_{name.upper()}_URL", down)
    with scripted_server(slow_to_say_ready) as server:
        monkeypatch.setenv("ROBOCLOUD_CAS_URL", server.url)
        done = CliRunner().invoke(app, ["status", "--json"])
        probes = [exchange.path for exchange in server.exchanges]
    assert done.exit_code == 3, done.output
    cas = json.loads(done.stdout)["services"][0]
    assert (cas["health"], cas["ready"]) == ("ok", "ready")
    assert probes == ["/healthz", "/readyz"]
    assert 0 <= cas["latency_ms"] < READY_AFTER_S * 1000
