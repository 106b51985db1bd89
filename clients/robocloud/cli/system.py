"""``robocloud status`` and ``robocloud whoami``: is the platform up, and does it know me."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import typer
from rich.table import Table

from robocloud.cli.context import JsonOption, KeystoreOption, load_identity
from robocloud.cli.exits import ExitCode, failure_of
from robocloud.cli.output import console, show, show_json, untrusted
from robocloud.client import ServiceClient
from robocloud.config import Endpoints
from robocloud.errors import RobocloudError

PROBE_TIMEOUT_S = 5.0


def _probe(client: ServiceClient, path: str) -> tuple[int, Any]:
    response = client.send("GET", path)
    try:
        body = client.json_of(response)
    except RobocloudError:
        body = None
    return response.status_code, body


def _status_of(name: str, url: str) -> tuple[dict[str, Any], ExitCode]:
    """One service's row. Its latency is the ``/healthz`` round trip alone: it included
    making the HTTP client (loading the CA bundle) and the ``/readyz`` probe, about 100 ms
    shown for services that answer in one or two."""
    row: dict[str, Any] = {"service": name, "url": url}
    try:
        with ServiceClient(url, service=name, retries=0, timeout=PROBE_TIMEOUT_S) as client:
            started = time.perf_counter()
            health, health_body = _probe(client, "/healthz")
            latency_ms = round((time.perf_counter() - started) * 1000)
            ready, _ = _probe(client, "/readyz")
    except RobocloudError as exc:
        failure = failure_of(exc)
        return {**row, "health": "down", "ready": None, "error": failure.message}, failure.code
    version = health_body.get("version") if isinstance(health_body, dict) else None
    row |= {
        "health": "ok" if health == 200 else health,
        "ready": "ready" if ready == 200 else ready,
        "version": version if isinstance(version, str) else None,
        "latency_ms": latency_ms,
    }
    return row, ExitCode.OK if health == 200 and ready == 200 else ExitCode.UNAVAILABLE


def status(as_json: bool = JsonOption) -> None:
    """Health, readiness and version of every service (exit 3 if one is unreachable, 5 if one
    is not ready)."""
    results = [_status_of(name, url) for name, url in Endpoints.from_env().items()]
    worst = max((code for _, code in results), default=ExitCode.OK)
    if as_json:
        show_json({"services": [row for row, _ in results], "ok": worst == ExitCode.OK})
    else:
        table = Table("service", "url", "health", "ready", "version", "latency")
        for row, _ in results:
            if row["health"] == "down":
                table.add_row(row["service"], row["url"], "[red]down[/]", "-", "-", "-")
                continue
            health_ok, ready_ok = row["health"] == "ok", row["ready"] == "ready"
            table.add_row(
                row["service"],
                row["url"],
                "[green]ok[/]" if health_ok else f"[red]{row['health']}[/]",
                "[green]ready[/]" if ready_ok else f"[yellow]{row['ready']}[/]",
                untrusted(row["version"] or "?", 40).replace("[", "\\["),
                f"{row['latency_ms']} ms",
            )
        console().print(table)
    if worst != ExitCode.OK:
        raise typer.Exit(int(worst))


def whoami(keystore: Path | None = KeystoreOption, as_json: bool = JsonOption) -> None:
    """Make a signed call to every service and show the address each one verified."""
    identity = load_identity(keystore)
    results: list[dict[str, Any]] = []
    worst = ExitCode.OK
    for name, url in Endpoints.from_env().items():
        try:
            with ServiceClient(url, identity, service=name, retries=0) as client:
                answer = client.post_json("/v1/whoami")
        except RobocloudError as exc:
            failure = failure_of(exc)
            results.append({"service": name, "address": None, "error": failure.message})
            worst = max(worst, failure.code)
            continue
        verified = answer.get("address") if isinstance(answer, dict) else None
        if verified != identity.address:
            worst = max(worst, ExitCode.INVALID_ANSWER)
        results.append({"service": name, "address": verified, "error": None})
    if as_json:
        show_json({"robot": identity.address, "services": results, "ok": worst == ExitCode.OK})
    else:
        table = Table("service", "verified address", "result")
        for row in results:
            if row["error"] is not None:
                table.add_row(row["service"], "-", f"[red]{_escaped(row['error'])}[/]")
            elif row["address"] == identity.address:
                table.add_row(row["service"], row["address"], "[green]ok[/]")
            else:
                table.add_row(row["service"], _escaped(row["address"]), "[red]mismatch[/]")
        show(f"robot {identity.address}")
        console().print(table)
    if worst != ExitCode.OK:
        raise typer.Exit(int(worst))


def _escaped(text: object) -> str:
    """Untrusted text inside a table cell that uses markup for colour."""
    return untrusted(text, 200).replace("[", "\\[")


def register(app: typer.Typer) -> None:
    app.command("status")(status)
    app.command("whoami")(whoami)
