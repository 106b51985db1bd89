"""``robocloud ingest BAG``: a bag into typed records, with a progress bar on stderr."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress

from robocloud.cas import Cas
from robocloud.cli.context import JsonOption, KeystoreOption, fail, load_identity
from robocloud.cli.output import console, show, show_json
from robocloud.ingest import Ingest

StorageOption = typer.Option(
    None,
    "--storage",
    help="URL of the storage service.",
    show_default="$ROBOCLOUD_STORAGE_URL, else http://127.0.0.1:8082",
)


def ingest(
    bag: Path = typer.Argument(
        ..., exists=True, help="A .bag, .mcap or .db3 file, or a ROS 2 bag directory."
    ),
    storage: str | None = StorageOption,
    cas: str | None = typer.Option(None, "--cas", help="URL of cas (for ROS 2 directories)."),
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Ingest a bag: every topic bound to an approved template becomes records.

    Waits for the job and prints what became of each topic; topics without an approved
    template are listed, not ingested.
    """
    identity = load_identity(keystore)
    with Ingest(storage, identity) as client:
        if bag.is_dir():
            with Cas(cas, identity) as cas_client:
                job = client.ingest(bag, cas_client)
        else:
            job = client.ingest(bag)
        stderr = console(stderr=True)
        columns = ("{task.description}", BarColumn(), MofNCompleteColumn())
        with Progress(*columns, console=stderr, transient=True, disable=as_json) as bar:
            task = bar.add_task("ingest", total=None)

            def advance(state: dict[str, Any]) -> None:
                messages = state["messages"]
                bar.update(task, completed=messages["done"], total=messages["total"] or None)

            job = client.wait(job["id"], advance)
    if as_json:
        show_json(job)
    else:
        show(f"job {job['id']}: {job['status']}, {job['records']['committed']} records")
        for topic in job["topics"]:
            show(
                f"  {topic['topic']} ({topic['msgtype']}): {topic['template'] or topic['skipped']}"
            )
    if job["status"] != "succeeded":
        fail(f"ingest failed: {job['error']['message']}")


def register(app: typer.Typer) -> None:
    app.command("ingest")(ingest)
