"""``robocloud ingest BAG``: a bag into typed records, with a progress bar on stderr."""

from __future__ import annotations

import json
import os
import stat
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress

from robocloud.cas import Cas
from robocloud.cli.context import JsonOption, KeystoreOption, StorageOption, fail, load_identity
from robocloud.cli.exits import ExitCode
from robocloud.cli.output import console, show, show_json, untrusted
from robocloud.ingest import FINISHED, WAIT_TIMEOUT_S, Ingest
from robocloud.partial import written_whole
from robocloud.templates import NAME as TEMPLATE_NAME


def ingest(
    bag: Path = typer.Argument(
        ..., exists=True, help="A .bag, .mcap or .db3 file, or a ROS 2 bag directory."
    ),
    storage: str | None = StorageOption,
    cas: str | None = typer.Option(None, "--cas", help="URL of cas (for ROS 2 directories)."),
    drafts: Path | None = typer.Option(
        None,
        "--drafts",
        file_okay=False,
        help="Write the draft template proposed for each unbound topic into this directory.",
    ),
    overwrite: bool = typer.Option(
        False, "--overwrite", help="Replace draft files that exist in the --drafts directory."
    ),
    wait_timeout: float = typer.Option(
        WAIT_TIMEOUT_S, "--timeout", min=0, help="Seconds to wait for the job to finish."
    ),
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Ingest a bag: every topic bound to an approved template becomes records.

    Waits for the job and prints what became of each topic; topics without an approved
    template are listed, not ingested, with the draft template their message definition gives
    (``--drafts DIR`` writes them out for ``robocloud templates create``).
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
        quiet = as_json or not stderr.is_terminal
        with Progress(*columns, console=stderr, transient=True, disable=quiet) as bar:
            task = bar.add_task("ingest", total=None)

            def advance(state: dict[str, Any]) -> None:
                messages = state["messages"]
                bar.update(task, completed=messages["done"], total=messages["total"] or None)

            job = client.wait(job["id"], advance, timeout_s=wait_timeout)
    if job["status"] not in FINISHED:
        fail(
            f"ingest job {job['id']} is still {job['status']} after {wait_timeout:g} s",
            ExitCode.UNAVAILABLE,
            f"the storage node goes on with it; follow it with robocloud job {job['id']} --wait",
        )
    _show_job(job, as_json)
    kept: list[Path] = []
    if drafts is not None:
        kept = _write_drafts(job, drafts, overwrite=overwrite)
        if not as_json:
            show(f"draft templates of unbound topics written to {drafts}")
    _fail_if_failed(job)
    if kept:
        fail(
            f"the ingest succeeded, but these files exist and were kept: "
            f"{', '.join(map(str, kept))}",
            hint="pass --overwrite to replace them with the drafts",
        )


def inspect_job(
    job_id: str = typer.Argument(..., help="The ingest job's id, as `robocloud ingest` printed."),
    wait: bool = typer.Option(False, "--wait", help="Wait for the job to finish."),
    resume: bool = typer.Option(
        False, "--resume", help="Run again a job that failed while committing (signed)."
    ),
    wait_timeout: float = typer.Option(
        WAIT_TIMEOUT_S, "--timeout", min=0, help="Seconds to wait, with --wait or --resume."
    ),
    storage: str | None = StorageOption,
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Show an ingest job: what became of each topic and of the dataset.

    For a job that `ingest` stopped waiting for, and for a dataset the node publishes later
    (its first attempt failed while cas or the ledger was out).
    """
    with Ingest(storage, load_identity(keystore) if resume else None) as client:
        state = client.resume(job_id) if resume else client.job(job_id)
        if wait or resume:
            state = client.wait(job_id, timeout_s=wait_timeout)
    _show_job(state, as_json)
    _fail_if_failed(state)


def _fail_if_failed(job: dict[str, Any]) -> None:
    """Exit non-zero for a failed job, saying how to run it again when it can be."""
    if job["status"] != "failed":
        return
    error = job.get("error") or {}
    hint = None
    if error.get("resumable") is True:
        hint = f"run it again with robocloud job {job['id']} --resume"
        until = error.get("resumable_until_ns")
        if isinstance(until, int) and not isinstance(until, bool):
            when = datetime.fromtimestamp(until / 1e9, tz=UTC)
            hint += f" before {when:%Y-%m-%d %H:%M} UTC, or after that send the bag again"
    fail(f"ingest failed: {error.get('message')}", hint=hint)


def _show_job(job: dict[str, Any], as_json: bool) -> None:
    if as_json:
        show_json(job)
    else:
        topics = (_topic_line(topic) for topic in job["topics"])
        show(_job_line(job), *topics, *_dataset_lines(job.get("dataset")))


def _job_line(job: dict[str, Any]) -> str:
    """The job's outcome as text; every part of it is the storage node's word."""
    committed = job["records"]["committed"]
    return f"job {untrusted(job['id'])}: {untrusted(job['status'])}, {untrusted(committed)} records"


def _dataset_lines(dataset: object) -> list[str]:
    """What became of the job's dataset, escaped: nothing when none was published (no
    records, or publishing off). A failure was said only in the node's log, so the robot
    never learned that its bag was neither advertised nor described."""
    if not isinstance(dataset, dict):
        return []
    if "error" in dataset:
        return [_unpublished_line(dataset)]
    return [
        f"dataset {untrusted(dataset.get('cid'), 100)}, described by "
        f"{untrusted(dataset.get('description'), 100)}, advertised in "
        f"{untrusted(dataset.get('tx'), 80)}"
    ]


def _unpublished_line(dataset: dict[str, Any]) -> str:
    """Why the dataset is not published, and whether the node tries again (and when)."""
    error, attempts = untrusted(dataset["error"]), dataset.get("attempts")
    next_attempt_ns = dataset.get("next_attempt_ns")
    if isinstance(next_attempt_ns, int):
        wait_s = max(0, round((next_attempt_ns - time.time_ns()) / 1e9))
        return (
            f"dataset not published yet: {error} (attempt {untrusted(attempts)}; the node "
            f"tries again in about {wait_s} s: see robocloud job ID)"
        )
    if isinstance(attempts, int) and attempts > 1:
        return f"dataset not published: {error} (after {attempts} attempts)"
    return f"dataset not published: {error}"


def _topic_line(topic: dict[str, Any]) -> str:
    """What became of one topic (why it was skipped, or else its template), escaped; for
    one bound to no template, the approved template that fits it, if one does."""
    outcome = topic.get("skipped") or topic.get("template")
    line = (
        f"  {untrusted(topic.get('topic'))} ({untrusted(topic.get('msgtype'))}): "
        f"{untrusted(outcome)}"
    )
    fits = topic.get("fits")
    if topic.get("template") is None and isinstance(fits, list) and fits:
        fitting = untrusted(fits[-1])
        line += f"; {fitting} fits it: robocloud bind {fitting} --topic {untrusted(topic['topic'])}"
    return line


def _write_drafts(job: dict[str, Any], directory: Path, *, overwrite: bool) -> list[Path]:
    """One ``<name>.json`` per proposed draft, named by the service: never a path it chose.

    Each file appears whole or not at all (an interrupted write leaves no half a draft for
    ``templates create`` to read). Topics of one type share a draft, written once (the node
    names distinct drafts apart). Without ``overwrite`` a file that exists, perhaps the
    operator's edit of an earlier draft, is kept: the paths kept are returned, but those
    holding the draft already.
    """
    directory.mkdir(parents=True, exist_ok=True)
    kept: list[Path] = []
    written: set[str] = set()
    for topic in job["topics"]:
        draft = topic.get("draft")
        if not isinstance(draft, dict) or not TEMPLATE_NAME.fullmatch(str(draft.get("name"))):
            continue
        if draft["name"] in written:
            continue
        written.add(draft["name"])
        target = directory / f"{draft['name']}.json"
        text = json.dumps(draft, indent=2, sort_keys=True).encode() + b"\n"
        try:
            with written_whole(target, overwrite=overwrite) as handle:
                handle.write(text)
        except FileExistsError:
            if not _holds(target, text):
                kept.append(target)
    return kept


def _holds(path: Path, data: bytes) -> bool:
    """Whether ``path`` is a file holding ``data`` exactly: a draft written by an earlier
    ingest and left as it was is no edit kept. A link is not followed, nor a FIFO waited on."""
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:
        return False
    with os.fdopen(descriptor, "rb") as file:
        status = os.fstat(descriptor)
        return (
            stat.S_ISREG(status.st_mode)
            and status.st_size == len(data)
            and file.read(len(data) + 1) == data
        )


def bind(
    template: str = typer.Argument(..., help="An approved template, name@version."),
    topic: str | None = typer.Option(None, "--topic", help="Bind this topic."),
    msgtype: str | None = typer.Option(
        None, "--msgtype", help="Bind this message type (a topic binding wins over it)."
    ),
    storage: str | None = StorageOption,
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Bind a topic or a message type to an approved template, for the next ingests."""
    if (topic is None) == (msgtype is None):
        raise typer.BadParameter("give exactly one of --topic and --msgtype")
    with Ingest(storage, load_identity(keystore)) as client:
        answer = client.bind(template, topic=topic, msgtype=msgtype)
    if as_json:
        show_json(answer)
    else:
        show(f"{topic or msgtype} -> {template}")


def register(app: typer.Typer) -> None:
    app.command("ingest")(ingest)
    app.command("job")(inspect_job)
    app.command("bind")(bind)
