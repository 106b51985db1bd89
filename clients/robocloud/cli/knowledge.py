"""``robocloud describe`` and ``robocloud sparql``: say what a file is, ask what others hold.

``describe`` builds each file's description here (media type from the name unless given,
width and height read from a JPEG or PNG header), validates it against the shapes before
anything leaves the robot, stores its canonical bytes in cas, has the storage node index it,
and with ``--advertise`` announces on chain that this robot holds the file, with the
description's CID beside it.
"""

from __future__ import annotations

import struct
import sys
from datetime import datetime
from pathlib import Path
from typing import Any

import typer

from robocloud import bounded_json
from robocloud.cas import Cas
from robocloud.cid import CID
from robocloud.cli.cas import CasOption
from robocloud.cli.context import (
    JsonOption,
    KeystoreOption,
    StorageOption,
    cid_argument,
    fail,
    load_identity,
)
from robocloud.cli.exits import ExitCode
from robocloud.cli.ledger import LedgerOption
from robocloud.cli.output import rows, show, show_json, untrusted
from robocloud.identity import Identity
from robocloud.knowledge import Knowledge
from robocloud.ledger import Ledger
from robocloud.semantic import (
    Description,
    DescriptionInvalidError,
    SemanticError,
    file_description,
    guess_media_type,
    sensor_iri,
)
from robocloud.unixfs import Importer

HEADER_BYTES = 1 << 16
"""Where an image's size is looked for: a JPEG's frame header comes before its pixels."""
MAX_LINE = 1 << 20
"""Characters of one line of a Turtle answer printed as text (the knowledge base's word)."""
FORMATS = {
    "json": "application/sparql-results+json",
    "xml": "application/sparql-results+xml",
    "csv": "text/csv",
    "turtle": "text/turtle",
    "ntriples": "application/n-triples",
    "rdfxml": "application/rdf+xml",
}


def image_size(header: bytes) -> tuple[int, int] | None:
    """(width, height) of a PNG (IHDR) or baseline/progressive JPEG (SOFn), else None."""
    if header[:8] == b"\x89PNG\r\n\x1a\n" and header[12:16] == b"IHDR" and len(header) >= 24:
        width, height = struct.unpack(">II", header[16:24])
        return (width, height) if width and height else None
    if header[:2] != b"\xff\xd8":
        return None
    position = 2
    while position + 9 <= len(header):
        if header[position] != 0xFF:
            return None
        marker = header[position + 1]
        if marker == 0xFF:
            position += 1
            continue
        (length,) = struct.unpack(">H", header[position + 2 : position + 4])
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            height, width = struct.unpack(">HH", header[position + 5 : position + 9])
            return (width, height) if width and height else None
        if length < 2:
            return None
        position += 2 + length
    return None


def _file_cid(path: Path) -> tuple[CID, int]:
    """The file's CID as ``robocloud put`` computes it, without sending it anywhere."""
    importer = Importer()
    with path.open("rb") as handle:
        while chunk := handle.read(1 << 20):
            importer.feed(chunk)
    _, cid, size = importer.finish()
    return cid, size


def _time(text: str | None, option: str) -> datetime | None:
    if text is None:
        return None
    try:
        value = datetime.fromisoformat(text)
    except ValueError:
        raise typer.BadParameter(
            f"{untrusted(text, 80)!r} is not an ISO 8601 time", param_hint=option
        ) from None
    if value.tzinfo is None:
        raise typer.BadParameter("give the time zone (2026-03-01T10:00:00Z)", param_hint=option)
    return value


def describe(
    files: list[Path] = typer.Argument(
        ...,
        exists=True,
        dir_okay=False,
        readable=True,
        metavar="FILE...",
        show_default=False,
        help="The files to describe.",
    ),
    media_type: str | None = typer.Option(
        None, "--media-type", help="IANA media type of every FILE.", show_default="from the name"
    ),
    title: str | None = typer.Option(None, help="A title.", show_default="the file's name"),
    sensor: list[str] = typer.Option(
        [], "--sensor", help="Name of a sensor of this robot that produced it (repeatable)."
    ),
    template: str | None = typer.Option(None, help="CID of the record template it follows."),
    start: str | None = typer.Option(None, help="ISO 8601 time its data starts."),
    end: str | None = typer.Option(None, help="ISO 8601 time its data ends."),
    width: int | None = typer.Option(None, help="Image width.", show_default="read from JPEG/PNG"),
    height: int | None = typer.Option(
        None, help="Image height.", show_default="read from JPEG/PNG"
    ),
    channels: int | None = typer.Option(None, help="Image channels."),
    encoding: str | None = typer.Option(None, help="Pixel or sample encoding (rgb8, ...)."),
    put: bool = typer.Option(True, help="Also add FILE itself to cas."),
    advertise: bool = typer.Option(
        False,
        "--advertise",
        help="Announce on chain that this robot holds FILE, with its description.",
    ),
    chain_id: int | None = typer.Option(
        None, "--chain-id", help="Chain of this robot's DID.", show_default="the ledger's"
    ),
    output: str | None = typer.Option(
        None,
        "--print",
        help="Print the description (turtle, rdfxml or ntriples) and store nothing.",
    ),
    cas: str | None = CasOption,
    storage: str | None = StorageOption,
    ledger_url: str | None = LedgerOption,
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Describe each FILE (what it holds, who made it), validate the description, store it in
    cas and have the knowledge base index it; print each file's CID and its description's."""
    if output is not None and output not in ("turtle", "rdfxml", "ntriples"):
        raise typer.BadParameter("turtle, rdfxml or ntriples", param_hint="--print")
    started, ended = _time(start, "--start"), _time(end, "--end")
    template_cid = cid_argument(template) if template is not None else None
    identity = load_identity(keystore)
    if chain_id is None:
        with Ledger.connect(ledger_url) as chain:
            chain_id = chain.chain_id
    robot = identity.did(chain_id)
    descriptions = []
    for path in files:
        file_cid, size = _file_cid(path)
        kind = media_type or guess_media_type(path.name)
        if kind is None:
            fail(f"cannot tell the media type of {path.name}", ExitCode.USAGE, "give --media-type")
        with path.open("rb") as handle:
            measured = image_size(handle.read(HEADER_BYTES))
        attributes: dict[str, Any] = {
            "width": width if width is not None else measured and measured[0],
            "height": height if height is not None else measured and measured[1],
            "channels": channels,
            "encoding": encoding,
        }
        try:
            description = file_description(
                file_cid,
                kind,
                size,
                title=title or path.name,
                producer=robot,
                sensors=[sensor_iri(robot, name) for name in sensor],
                template=template_cid,
                start=started,
                end=ended,
                attributes={name: value for name, value in attributes.items() if value},
            )
        except SemanticError as exc:
            fail(f"{path.name}: {exc}", ExitCode.USAGE)
        try:
            _validated(description)
        except DescriptionInvalidError as exc:
            fail(f"{path.name}: {exc}", ExitCode.USAGE)
        descriptions.append((path, file_cid, description))
    if output is not None:
        for _, _, description in descriptions:
            _print_description(description, output)
        return
    results = _store(descriptions, identity, cas, storage, ledger_url, put=put, advertise=advertise)
    if as_json:
        show_json(results)
        return
    for result in results:
        lines = [
            ("file", result["file"]),
            ("cid", result["cid"]),
            ("description", result["description"]),
        ]
        if "tx" in result:
            lines.append(("advertised", result["tx"]))
        show(*rows(lines))


def _validated(description: Description) -> None:
    from robocloud.semantic import validate

    validate(description)


def _print_description(description: Description, output: str) -> None:
    if output == "turtle":
        sys.stdout.write(description.turtle())
    elif output == "rdfxml":
        sys.stdout.write(description.rdf_xml())
    else:
        sys.stdout.buffer.write(description.canonical())
        sys.stdout.flush()


def _store(
    descriptions: list[tuple[Path, CID, Description]],
    identity: Identity,
    cas_url: str | None,
    storage_url: str | None,
    ledger_url: str | None,
    *,
    put: bool,
    advertise: bool,
) -> list[dict[str, Any]]:
    results: list[dict[str, Any]] = []
    with Cas(cas_url, identity) as cas, Knowledge(storage_url, identity) as knowledge:
        for path, file_cid, description in descriptions:
            if put:
                cas.add_file(path)
            described = knowledge.store(description, cas)
            results.append({"file": str(path), "cid": str(file_cid), "description": str(described)})
    if advertise:
        with Ledger.connect(ledger_url, identity) as chain:
            for result in results:
                event = chain.advertise(
                    CID.decode(result["cid"]).binary, CID.decode(result["description"]).binary
                )
                result["tx"] = event.tx_hash
    return results


def _query_text(query: str) -> str:
    """The query itself, or the text of the file (``@FILE``) or of stdin (``-``) it names."""
    if query != "-" and not query.startswith("@"):
        return query
    raw = sys.stdin.buffer.read() if query == "-" else Path(query[1:]).read_bytes()
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        where = "stdin" if query == "-" else query[1:]
        raise typer.BadParameter(f"{where} is not UTF-8 text: {exc}", param_hint="QUERY") from exc


def sparql(
    query: str = typer.Argument(
        ...,
        help="The SPARQL query, @FILE to read it from a file, or - for stdin.",
        show_default=False,
    ),
    output: str = typer.Option(
        "table",
        "--format",
        help="table (rows as tab-separated text), or the answer as json, xml, csv, turtle, "
        "ntriples or rdfxml.",
    ),
    storage: str | None = StorageOption,
    as_json: bool = typer.Option(
        False, "--json", help="Print the answer as SPARQL JSON results (--format json)."
    ),
) -> None:
    """Ask the knowledge base a SPARQL query and print the answer."""
    if as_json:
        output = "json"
    if output != "table" and output not in FORMATS:
        raise typer.BadParameter(f"table or one of {', '.join(FORMATS)}", param_hint="--format")
    text = _query_text(query)
    accept = (
        "application/sparql-results+json, text/turtle;q=0.9"
        if output == "table"
        else FORMATS[output]
    )
    with Knowledge(storage) as knowledge:
        answer = knowledge.sparql(text, accept=accept)
    if output != "table":
        sys.stdout.buffer.write(answer.body)
        sys.stdout.flush()
    elif answer.media_type != "application/sparql-results+json":
        for line in answer.body.decode("utf-8", "replace").splitlines():
            typer.echo(untrusted(line, MAX_LINE))
    else:
        _print_table(bounded_json.loads(answer.body))


def _print_table(document: Any) -> None:
    """SPARQL JSON results as tab-separated lines, every name and value escaped."""
    if isinstance(document, dict) and "boolean" in document:
        show("yes" if document["boolean"] is True else "no")
        return
    try:
        names = [str(name) for name in document["head"]["vars"]]
        bindings = document["results"]["bindings"]
        table = [
            "\t".join(untrusted(row.get(name, {}).get("value", ""), 400) for name in names)
            for row in bindings
        ]
    except (KeyError, TypeError, AttributeError) as exc:
        fail(
            f"the knowledge base's answer is not SPARQL JSON results: {exc}",
            ExitCode.INVALID_ANSWER,
        )
    header = "\t".join(untrusted(name, 200) for name in names)
    for line in [header, *table]:  # tab-separated as it is: rich expands tabs
        typer.echo(line)


def register(app: typer.Typer) -> None:
    app.command("describe")(describe)
    app.command("sparql")(sparql)
