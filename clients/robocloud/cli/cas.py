"""``robocloud put``, ``get``, ``pin``, ``unpin``, ``pins``: files in the content store."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import typer
from rich.progress import BarColumn, DownloadColumn, Progress, TransferSpeedColumn

from robocloud.cas import Cas, CasError
from robocloud.cid import CID
from robocloud.cli.context import KeystoreOption, console, fail, load_identity
from robocloud.errors import ApiError
from robocloud.unixfs import ImportParams, UnixfsError

CasOption = typer.Option(
    None, "--cas", help="Gateway URL [default: $ROBOCLOUD_CAS_URL or loopback]"
)
PROGRESS_THRESHOLD = 8 << 20


def parse_cid(text: str) -> CID:
    try:
        return CID.decode(text)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc


@contextmanager
def _errors() -> Iterator[None]:
    try:
        yield
    except (ApiError, CasError, UnixfsError, httpx.HTTPError) as exc:
        raise fail(str(exc)) from exc


@contextmanager
def _progress(label: str, total: int | None) -> Iterator[Callable[[int], None]]:
    """A transfer bar for large files only; small ones finish before a bar would help."""
    if total is not None and total < PROGRESS_THRESHOLD:
        yield lambda _: None
        return
    columns = ("{task.description}", BarColumn(), DownloadColumn(), TransferSpeedColumn())
    with Progress(*columns, console=console, transient=True) as bar:
        task = bar.add_task(label, total=total)
        yield lambda size: bar.advance(task, size)


def put(
    file: Path = typer.Argument(..., exists=True, dir_okay=False, readable=True),
    pin: bool = typer.Option(True, help="Pin the content to this robot"),
    cid_version: int = typer.Option(1, "--cid-version"),
    chunker: str = typer.Option("size-262144", help="size-<bytes>"),
    cas: str | None = CasOption,
    keystore: Path | None = KeystoreOption,
) -> None:
    """Add a file; print its CID (checked against the CID computed here)."""
    with _errors():
        params = ImportParams.from_options(cid_version=cid_version, chunker=chunker)
    identity = load_identity(keystore)
    with _errors(), Cas(cas, identity) as client, _progress("put", file.stat().st_size) as advance:
        cid = client.add_file(file, pin=pin, params=params, progress=advance)
    console.print(str(cid))


def get(
    cid: str = typer.Argument(..., help="CID of a file"),
    output: Path = typer.Option(..., "--output", "-o", help="Where to write the content"),
    cas: str | None = CasOption,
) -> None:
    """Fetch a file, verifying every block against its CID."""
    root = parse_cid(cid)
    with _errors(), Cas(cas) as client, _progress("get", None) as advance:
        size = client.get_to_file(root, output, progress=advance)
    console.print(f"{root} -> {output} ({size} bytes, verified)")


def pin(
    cid: str = typer.Argument(...),
    cas: str | None = CasOption,
    keystore: Path | None = KeystoreOption,
) -> None:
    """Pin content to this robot so garbage collection keeps it."""
    root = parse_cid(cid)
    identity = load_identity(keystore)
    with _errors(), Cas(cas, identity) as client:
        client.pin(root)
    console.print(f"pinned {root}")


def unpin(
    cid: str = typer.Argument(...),
    cas: str | None = CasOption,
    keystore: Path | None = KeystoreOption,
) -> None:
    """Remove this robot's pin."""
    root = parse_cid(cid)
    identity = load_identity(keystore)
    with _errors(), Cas(cas, identity) as client:
        client.unpin(root)
    console.print(f"unpinned {root}")


def pins(cas: str | None = CasOption) -> None:
    """List pinned CIDs and the robots that pinned them."""
    with _errors(), Cas(cas) as client:
        for cid, info in sorted(client.pins().items()):
            console.print(f"{cid}  {' '.join(info.get('Owners', []))}")


def register(app: typer.Typer) -> None:
    for command in (put, get, pin, unpin, pins):
        app.command(command.__name__)(command)
