"""``robocloud templates ...``, ``query``, ``export`` and ``intervals``: typed records in the
storage service."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

from robocloud.cli.context import JsonOption, KeystoreOption, StorageOption, fail, load_identity
from robocloud.cli.exits import ExitCode
from robocloud.cli.output import rows, show, show_json, untrusted
from robocloud.errors import FormatError
from robocloud.ingest import Ingest
from robocloud.storage import Storage, TemplateVersion, record_filters
from robocloud.templates import load_template_document, parse_template_id, type_to_json

MAX_TEMPLATE_FILE = 256 * 1024

templates_app = typer.Typer(
    name="templates", help="Design, version and review record templates.", no_args_is_help=True
)


def _document(file: Path) -> Any:
    """The template document in ``file``: a file that is not one is the command's mistake
    (exit 2), not the service's (exit 6, which a ``FormatError`` would otherwise get)."""
    if file.stat().st_size > MAX_TEMPLATE_FILE:
        fail(f"{file} is larger than {MAX_TEMPLATE_FILE} bytes", ExitCode.USAGE)
    try:
        return load_template_document(file.read_bytes())
    except FormatError as exc:
        fail(f"{file}: {exc}", ExitCode.USAGE)


def _template_id(text: str) -> str:
    """A ``name@version`` argument, checked here so a bad one is a usage error (exit 2)."""
    try:
        parse_template_id(text)
    except FormatError as exc:
        raise typer.BadParameter(str(exc)) from exc
    return text


TemplateId = typer.Argument(..., metavar="ID", help="name@version", callback=_template_id)


def _show_version(version: TemplateVersion, as_json: bool) -> None:
    document = {
        "id": version.id,
        "status": version.status,
        "author": version.author,
        "reviewer": version.reviewer,
        "reason": version.reason,
        **version.template.to_json(),
    }
    if as_json:
        show_json(document)
        return
    fields = ", ".join(
        f"{name}: {json.dumps(type_to_json(kind))}"
        for name, kind in version.template.fields.items()
    )
    show(
        *rows(
            [
                ("id", untrusted(version.id)),
                ("status", untrusted(version.status)),
                ("author", untrusted(version.author)),
                ("reviewer", untrusted(version.reviewer or "-")),
                ("reason", untrusted(version.reason or "-")),
                ("fields", untrusted(fields, 2000)),
                ("description", untrusted(version.template.description or "-")),
            ]
        )
    )


TemplateFile = typer.Argument(
    ..., exists=True, dir_okay=False, readable=True, metavar="FILE", help="Template JSON."
)


@templates_app.command("create")
def create(
    file: Path = TemplateFile,
    storage: str | None = StorageOption,
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Create a template (version 1, a draft) from a JSON file."""
    document = _document(file)
    with Storage(storage, load_identity(keystore)) as client:
        _show_version(client.create_template(document), as_json)


@templates_app.command("version")
def new_version(
    name: str = typer.Argument(..., help="Template name."),
    file: Path = TemplateFile,
    storage: str | None = StorageOption,
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Make the next version of a template (a draft) from a JSON file of its fields."""
    document = _document(file)
    with Storage(storage, load_identity(keystore)) as client:
        _show_version(client.new_version(name, document), as_json)


@templates_app.command("edit")
def edit(
    template_id: str = TemplateId,
    file: Path = TemplateFile,
    storage: str | None = StorageOption,
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Replace a draft's fields (approved versions never change: make a new version)."""
    document = _document(file)
    with Storage(storage, load_identity(keystore)) as client:
        _show_version(client.edit_template(template_id, document), as_json)


@templates_app.command("submit")
def submit(
    template_id: str = TemplateId,
    storage: str | None = StorageOption,
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Submit a draft for review."""
    with Storage(storage, load_identity(keystore)) as client:
        _show_version(client.submit_template(template_id), as_json)


@templates_app.command("review")
def review(
    template_id: str = TemplateId,
    decision: str = typer.Argument(..., help="approve or reject"),
    reason: str | None = typer.Option(None, help="Why (shown to the author)."),
    storage: str | None = StorageOption,
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Approve or reject a submitted version (needs the reviewer role)."""
    if decision not in ("approve", "reject"):
        raise typer.BadParameter("approve or reject", param_hint="DECISION")
    with Storage(storage, load_identity(keystore)) as client:
        _show_version(client.review_template(template_id, decision, reason), as_json)


@templates_app.command("show")
def show_template(
    template_id: str = TemplateId,
    storage: str | None = StorageOption,
    as_json: bool = JsonOption,
) -> None:
    """Show one template version."""
    with Storage(storage) as client:
        _show_version(client.template(template_id), as_json)


@templates_app.command("list")
def list_templates(
    name: str | None = typer.Option(None, help="Only this template's versions."),
    status: str | None = typer.Option(None, help="draft, submitted, approved or rejected."),
    storage: str | None = StorageOption,
    as_json: bool = JsonOption,
) -> None:
    """List template versions."""
    with Storage(storage) as client:
        versions = list(client.templates(name=name, status=status))
    if as_json:
        show_json([{"id": v.id, "status": v.status, "author": v.author} for v in versions])
        return
    show(
        *(
            f"{untrusted(v.id):<40} {untrusted(v.status, 10):<10} {untrusted(v.author)}"
            for v in versions
        )
    )


TemplateFilter = typer.Option(None, "--template", help="Template id name@version.")
TopicFilter = typer.Option(None, "--topic", help="ROS topic.")
RobotFilter = typer.Option(None, "--robot", help="Robot address.")
StartFilter = typer.Option(None, "--start", min=0, help="t >= START (ns).")
EndFilter = typer.Option(None, "--end", min=0, help="t < END (ns).")
WhereFilter = typer.Option([], "--where", help="field op value (= != < <= > >=); repeatable.")
KeywordsFilter = typer.Option(None, "--keywords", help="Words every record must hold.")


def query(
    template: str | None = TemplateFilter,
    topic: str | None = TopicFilter,
    robot: str | None = RobotFilter,
    start: int | None = StartFilter,
    end: int | None = EndFilter,
    where: list[str] = WhereFilter,
    keywords: str | None = KeywordsFilter,
    limit: int = typer.Option(100, min=1, max=1000, help="Records per page."),
    cursor: str | None = typer.Option(None, help="Continue after a previous page."),
    storage: str | None = StorageOption,
    as_json: bool = JsonOption,
) -> None:
    """Query records: a table, or one JSON document with --json (its next continues it)."""
    with Storage(storage) as client:
        page = client.query(
            template=template,
            topic=topic,
            robot=robot,
            start=start,
            end=end,
            where=where,
            keywords=keywords,
            limit=limit,
            cursor=cursor,
        )
    if as_json:
        show_json(
            {
                "records": [
                    {"id": item.id, "record": item.record, "signer": item.signer}
                    for item in page.records
                ],
                "next": page.next,
            }
        )
        return
    lines = [f"{'id':<28} {'t':>20} {'topic':<20} data"]
    for item in page.records:
        data = json.dumps(item.record.get("data"), separators=(",", ":"))
        record_id, t = untrusted(item.id, 80), untrusted(item.record.get("t"), 20)
        topic_text = untrusted(item.record.get("topic"), 20)
        lines.append(f"{record_id:<28} {t:>20} {topic_text:<20} {untrusted(data, 200)}")
    if page.next is not None:
        lines.append(f"more: --cursor {untrusted(page.next, 1000)}")
    show(*lines)


EXPORT_SUFFIXES = {".mcap": "mcap", ".jsonl": "jsonl", ".ndjson": "jsonl"}


def export(
    output: Path = typer.Argument(
        ..., dir_okay=False, help="The file to write: .mcap, or .jsonl (one record a line)."
    ),
    export_format: str | None = typer.Option(
        None,
        "--format",
        help="mcap or jsonl.",
        show_default="from OUTPUT's suffix",
    ),
    template: str | None = TemplateFilter,
    topic: str | None = TopicFilter,
    robot: str | None = RobotFilter,
    start: int | None = StartFilter,
    end: int | None = EndFilter,
    where: list[str] = WhereFilter,
    keywords: str | None = KeywordsFilter,
    limit: int = typer.Option(1_000_000, min=1, max=10_000_000, help="At most this many records."),
    force: bool = typer.Option(False, "--force", "-f", help="Replace OUTPUT if it exists."),
    storage: str | None = StorageOption,
    as_json: bool = JsonOption,
) -> None:
    """Export the records a query selects to an MCAP or JSON-lines file.

    The file appears only once the whole export arrived; one that fails leaves nothing.
    MCAP carries each template as a JSON Schema and each record as a JSON message, which
    the mcap library and Foxglove read.
    """
    chosen = export_format or EXPORT_SUFFIXES.get(output.suffix.lower())
    if chosen not in ("mcap", "jsonl"):
        raise typer.BadParameter(
            "mcap or jsonl (OUTPUT's suffix does not say which)", param_hint="--format"
        )
    if (output.exists() or output.is_symlink()) and not force:
        fail(f"{output} exists", hint="pass --force to replace it")
    params = record_filters(
        template=template,
        topic=topic,
        robot=robot,
        start=start,
        end=end,
        where=where,
        keywords=keywords,
    )
    params |= {"format": chosen, "limit": limit}
    with Ingest(storage) as client:
        try:
            size = client.export(params, output, overwrite=force)
        except FileExistsError:
            fail(f"{output} appeared while exporting", hint="pass --force to replace it")
    if as_json:
        show_json({"path": str(output), "format": chosen, "size": size})
    else:
        show(f"{chosen} export -> {output} ({size} bytes)")


def intervals(
    template: str = typer.Option(..., "--template", help="Template id name@version."),
    field: str = typer.Option(..., "--field", help="The field, a dotted path."),
    value: str = typer.Option(..., "--value", help="The state: the field's value."),
    robot: str | None = RobotFilter,
    start: int | None = StartFilter,
    end: int | None = EndFilter,
    storage: str | None = StorageOption,
    as_json: bool = JsonOption,
) -> None:
    """When each robot entered and left a state (a field holding a value), from its records."""
    with Storage(storage) as client:
        found = client.intervals(template, field, value, robot=robot, start=start, end=end)
    if as_json:
        show_json(
            {
                "template": template,
                "field": field,
                "value": value,
                "intervals": [interval.to_json() for interval in found],
            }
        )
        return
    lines = [f"{'robot':<42} {'enter':>20} {'exit':>20}"]
    for interval in found:
        left = "still in" if interval.exit is None else str(interval.exit)
        lines.append(f"{untrusted(interval.robot, 42):<42} {interval.enter:>20} {left:>20}")
    show(*lines)


def register(app: typer.Typer) -> None:
    app.add_typer(templates_app)
    app.command("query")(query)
    app.command("export")(export)
    app.command("intervals")(intervals)
