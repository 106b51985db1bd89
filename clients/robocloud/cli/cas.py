"""``robocloud put``, ``get``, ``cat``, ``pin``, ``unpin``, ``pins``, ``pinned``: files in the
content store."""

from __future__ import annotations

import base64
import dataclasses
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import typer
from rich.progress import BarColumn, DownloadColumn, Progress, TransferSpeedColumn

from robocloud.cas import Cas, ContentTooLargeError, NotAFileError, is_directory
from robocloud.cid import CID
from robocloud.cli.context import (
    JsonOption,
    KeystoreOption,
    cid_argument,
    content_argument,
    fail,
    load_identity,
    parse_size,
)
from robocloud.cli.exits import ExitCode
from robocloud.cli.output import console, show, show_json, size_text, untrusted
from robocloud.partial import free_space_beside
from robocloud.unixfs import ImportParams, UnixfsError

CasOption = typer.Option(
    None,
    "--cas",
    help="URL of the cas service (or any kubo-compatible gateway).",
    show_default="$ROBOCLOUD_CAS_URL, else http://127.0.0.1:8080",
)
PROGRESS_THRESHOLD = 8 << 20


@contextmanager
def _progress(label: str, total: int | None) -> Iterator[Callable[[int], None]]:
    """A transfer bar on stderr, for large or unknown sizes and only on a terminal."""
    stderr = console(stderr=True)
    if (total is not None and total < PROGRESS_THRESHOLD) or not stderr.is_terminal:
        yield lambda _: None
        return
    columns = ("{task.description}", BarColumn(), DownloadColumn(), TransferSpeedColumn())
    with Progress(*columns, console=stderr, transient=True) as bar:
        task = bar.add_task(label, total=total)
        yield lambda size: bar.advance(task, size)


def put(
    path: Path = typer.Argument(
        ...,
        exists=True,
        readable=True,
        metavar="PATH",
        help="The file, or the directory to add with everything under it.",
    ),
    pin: bool = typer.Option(True, help="Pin the content to this robot."),
    cid_version: int = typer.Option(1, "--cid-version", help="CID version: 0 or 1."),
    chunker: str = typer.Option("size-262144", help="Chunk size, as size-<bytes>."),
    hidden: bool = typer.Option(
        False, "--hidden", help="Include files and directories whose names start with '.'."
    ),
    cas: str | None = CasOption,
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Add a file or a directory (as ipfs add -r) and print its CID, checked against the CID
    computed here.

    Only the CID goes to stdout, so CID=$(robocloud put PATH) works for any size.
    """
    try:
        params = ImportParams.from_options(cid_version=cid_version, chunker=chunker)
    except UnixfsError as exc:
        raise typer.BadParameter(str(exc), param_hint="--cid-version/--chunker") from exc
    identity = load_identity(keystore)
    size = _tree_size(path, hidden) if path.is_dir() else path.stat().st_size
    with Cas(cas, identity) as client, _progress("put", size) as advance:
        if path.is_dir():
            cid = client.add_directory(
                path, pin=pin, params=params, hidden=hidden, progress=advance
            )
        else:
            cid = client.add_file(path, pin=pin, params=params, progress=advance)
    if as_json:
        show_json({"cid": str(cid), "size": size, "pinned": pin})
    else:
        show(str(cid))


def _tree_size(root: Path, hidden: bool) -> int:
    """The bytes of the files ``put`` sends, for its progress bar."""
    return sum(
        entry.stat().st_size
        for entry in root.rglob("*")
        if entry.is_file()
        and (hidden or not any(part.startswith(".") for part in entry.relative_to(root).parts))
    )


def get(
    cid: str = typer.Argument(
        ...,
        help="CID of a file or a directory, or CID/PATH of an entry of a directory.",
        metavar="CID[/PATH]",
        show_default=False,
    ),
    output: Path = typer.Option(..., "--output", "-o", help="Where to write the verified content."),
    force: bool = typer.Option(
        False, "--force", "-f", help="Replace OUTPUT if it exists (a file, not a directory)."
    ),
    max_size: int | None = typer.Option(
        None,
        "--max-size",
        parser=parse_size,
        metavar="SIZE",
        help="Refuse a file larger than this: bytes, or a number with kB, MB, GB, KiB, MiB, GiB.",
        show_default="the free space in OUTPUT's directory",
    ),
    cas: str | None = CasOption,
    as_json: bool = JsonOption,
) -> None:
    """Fetch a file, or a directory as ipfs get does, verifying every block against its CID.

    OUTPUT appears only once all of it is verified; a failed or refused download leaves
    nothing behind. A directory's entries are checked to be plain names, so none is written
    outside OUTPUT, and --max-size bounds its files' bytes in all.
    """
    directory_cid, path = content_argument(cid)
    if (output.exists() or output.is_symlink()) and not force:
        fail(f"{output} exists", hint="pass --force to replace it")
    if max_size is None:
        limit, why = free_space_beside(output), f"the free space in {output.absolute().parent}"
    else:
        limit, why = max_size, "--max-size"
    with Cas(cas) as client, _progress("get", None) as advance:
        root = client.resolve(directory_cid, path) if path else directory_cid
        try:
            size, files = _fetched(client, root, output, advance, limit, force)
        except ContentTooLargeError as exc:
            fail(
                f"{exc}; nothing was written",
                ExitCode.ERROR,
                f"the limit is {why}, {size_text(limit)}; pass a larger --max-size",
            )
        except FileExistsError:
            fail(f"{output} appeared while downloading", hint="pass --force to replace it")
    if as_json:
        answer = {"cid": str(root), "path": str(output), "size": size, "verified": True}
        show_json(answer if files is None else answer | {"files": files})
    elif files is None:
        show(f"{root} -> {output} ({size} bytes, verified)")
    else:
        show(f"{root} -> {output} ({files} files, {size} bytes, verified)")


def _fetched(
    client: Cas,
    root: CID,
    output: Path,
    advance: Callable[[int], None],
    limit: int,
    force: bool,
) -> tuple[int, int | None]:
    """``root`` written to ``output``: a file's size and None, or a directory's size and
    files. A file is asked for first, so that fetching one costs no more than before."""
    try:
        return client.get_to_file(root, output, advance, max_size=limit, overwrite=force), None
    except NotAFileError as exc:
        if not is_directory(exc):
            raise
    if output.exists() or output.is_symlink():
        fail(f"{output} exists", hint="a directory replaces nothing: remove it first")
    tree = client.get_tree(root, output, advance, max_size=limit)
    return tree.size, tree.files


def cat(
    cid: str = typer.Argument(
        ...,
        help="CID of the file, or CID/PATH of a file in a directory.",
        metavar="CID[/PATH]",
        show_default=False,
    ),
    offset: int = typer.Option(0, "--offset", min=0, help="The first byte to print."),
    length: int | None = typer.Option(
        None, "--length", min=0, help="How many bytes to print.", show_default="to the end"
    ),
    cas: str | None = CasOption,
    as_json: bool = JsonOption,
) -> None:
    """Print a file, or the byte range --offset/--length of it, verified against its CID.

    Only the blocks the range needs are fetched. The bytes are checked before any is printed,
    so at most 64 MiB; get writes a larger file. With --json the bytes are base64 in
    "content_base64".
    """
    directory_cid, path = content_argument(cid)
    with Cas(cas) as client:
        root = client.resolve(directory_cid, path) if path else directory_cid
        try:
            data = client.cat(root, offset, length)
        except ContentTooLargeError as exc:
            fail(str(exc), ExitCode.ERROR, "print a smaller --length, or use get -o FILE")
    if as_json:
        show_json(
            {
                "cid": str(root),
                "offset": offset,
                "size": len(data),
                "verified": True,
                "content_base64": base64.b64encode(data).decode(),
            }
        )
        return
    sys.stdout.buffer.write(data)
    sys.stdout.buffer.flush()


def pin(
    cid: str = typer.Argument(..., help="CID to pin.", metavar="CID", show_default=False),
    cas: str | None = CasOption,
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Pin content to this robot so garbage collection keeps it."""
    _set_pin(cid, True, cas, keystore, as_json)


def unpin(
    cid: str = typer.Argument(..., help="CID to unpin.", metavar="CID", show_default=False),
    cas: str | None = CasOption,
    keystore: Path | None = KeystoreOption,
    as_json: bool = JsonOption,
) -> None:
    """Remove this robot's pin."""
    _set_pin(cid, False, cas, keystore, as_json)


def _set_pin(cid: str, pinned: bool, cas: str | None, keystore: Path | None, as_json: bool) -> None:
    root = cid_argument(cid)
    with Cas(cas, load_identity(keystore)) as client:
        if pinned:
            client.pin(root)
        else:
            client.unpin(root)
    if as_json:
        show_json({"cid": str(root), "pinned": pinned})
    else:
        show(f"{'pinned' if pinned else 'unpinned'} {root}")


def pins(cas: str | None = CasOption, as_json: bool = JsonOption) -> None:
    """List pinned CIDs and the robots that pinned them."""
    with Cas(cas) as client:
        listed = sorted(client.pins().items())
    if as_json:
        show_json(
            {
                "pins": [
                    {"cid": cid, "type": info.get("Type"), "owners": info.get("Owners", [])}
                    for cid, info in listed
                ]
            }
        )
        return
    show(*(untrusted(" ".join([cid, *info.get("Owners", [])]), 10_000) for cid, info in listed))


def pinned(
    cas: str | None = CasOption, keystore: Path | None = KeystoreOption, as_json: bool = JsonOption
) -> None:
    """How many bytes this robot keeps pinned and wrote in the last hour, and the most it
    may."""
    with Cas(cas, load_identity(keystore)) as client:
        share = client.pin_share()
    if as_json:
        show_json(dataclasses.asdict(share))
        return
    show(
        f"{share.robot} keeps {size_text(share.pinned_bytes)} pinned "
        f"({_bound(share.max_bytes)}) and wrote {size_text(share.written_bytes_last_hour)} "
        f"in the last hour ({_bound(share.max_written_bytes_per_hour)})"
    )


def _bound(limit: int | None) -> str:
    return "no bound" if limit is None else f"at most {size_text(limit)}"


def register(app: typer.Typer) -> None:
    for command in (put, get, cat, pin, unpin, pins, pinned):
        app.command(command.__name__)(command)
