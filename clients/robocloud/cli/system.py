"""``robocloud status`` and ``robocloud whoami``: is the platform up, and does it know me."""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import typer
from rich.table import Table

from robocloud.cli.context import KeystoreOption, console, load_identity
from robocloud.client import ServiceClient
from robocloud.config import Endpoints
from robocloud.errors import ApiError


def status() -> None:
    """Health, readiness and version of every service."""
    table = Table("service", "url", "health", "ready", "version", "latency")
    all_ok = True
    for name, url in Endpoints.from_env().items():
        started = time.perf_counter()
        try:
            health = httpx.get(f"{url}/healthz", timeout=5)
            ready = httpx.get(f"{url}/readyz", timeout=5)
        except httpx.HTTPError as exc:
            table.add_row(name, url, f"[red]down[/] ({type(exc).__name__})", "-", "-", "-")
            all_ok = False
            continue
        latency = f"{(time.perf_counter() - started) * 1000:.0f} ms"
        ok = health.status_code == 200 and ready.status_code == 200
        all_ok = all_ok and ok
        version = health.json().get("version", "?") if health.status_code == 200 else "-"
        table.add_row(
            name,
            url,
            "[green]ok[/]" if health.status_code == 200 else f"[red]{health.status_code}[/]",
            "[green]ready[/]" if ready.status_code == 200 else f"[yellow]{ready.status_code}[/]",
            version,
            latency,
        )
    console.print(table)
    if not all_ok:
        raise typer.Exit(1)


def whoami(keystore: Path | None = KeystoreOption) -> None:
    """Make a signed call to every service and show the address each one verified."""
    identity = load_identity(keystore)
    table = Table("service", "verified address", "result")
    all_ok = True
    for name, url in Endpoints.from_env().items():
        with ServiceClient(url, identity, retries=0) as client:
            try:
                answer = client.post_json("/v1/whoami")
            except (ApiError, httpx.HTTPError) as exc:
                table.add_row(name, "-", f"[red]{exc}[/]")
                all_ok = False
                continue
        matches = answer["address"] == identity.address
        all_ok = all_ok and matches
        table.add_row(name, answer["address"], "[green]ok[/]" if matches else "[red]mismatch[/]")
    console.print(f"robot {identity.address}")
    console.print(table)
    if not all_ok:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    app.command("status")(status)
    app.command("whoami")(whoami)
