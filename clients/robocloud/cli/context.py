"""What every command needs: the robot's identity, shared options, and failing in one form."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import NoReturn

import typer

from robocloud.cid import CID, CIDError, parse_cid
from robocloud.cli.exits import ExitCode, Failure, report
from robocloud.cli.output import untrusted
from robocloud.directory import split_path
from robocloud.errors import KeystoreError
from robocloud.identity import PASSPHRASE_ENV, Identity, default_keystore_path
from robocloud.unixfs import UnixfsError

JsonOption = typer.Option(False, "--json", help="Print one JSON document instead of text.")
StorageOption = typer.Option(
    None,
    "--storage",
    help="URL of the storage service (records, templates, ingestion, knowledge base).",
    show_default="$ROBOCLOUD_STORAGE_URL, else http://127.0.0.1:8082",
)
KeystoreOption = typer.Option(
    None,
    "--keystore",
    "-k",
    help="The robot's encrypted keystore file.",
    show_default="$ROBOCLOUD_KEYSTORE, else ~/.robocloud/keystore.json",
    dir_okay=False,
)


def passphrase(*, confirm: bool = False) -> str:
    """``$ROBOCLOUD_PASSPHRASE`` for scripts and robots, else an interactive prompt (stderr)."""
    from_env = os.environ.get(PASSPHRASE_ENV)
    if from_env:
        return from_env
    try:
        return str(
            typer.prompt(
                "Keystore passphrase", hide_input=True, confirmation_prompt=confirm, err=True
            )
        )
    except typer.Abort as exc:  # click's answer to both Ctrl-C and no terminal (EOF)
        raise KeystoreError(
            f"no passphrase given (interrupted, or no terminal to ask on); scripts and robots "
            f"set {PASSPHRASE_ENV}"
        ) from exc


def keystore_path(keystore: Path | None) -> Path:
    return keystore or default_keystore_path()


def load_identity(keystore: Path | None) -> Identity:
    """The robot's key; a ``KeystoreError`` (with its hint) is reported by the CLI's handler."""
    return Identity.load(keystore_path(keystore), passphrase())


def fail(message: str, code: ExitCode = ExitCode.ERROR, hint: str | None = None) -> NoReturn:
    """Report a failure found by the command itself, in the same one-line form, and exit."""
    report(Failure(code, message, hint))
    raise typer.Exit(int(code))


_SIZE = re.compile(r"\s*(\d+)\s*([kmgtp]i?b|b)?\s*", re.IGNORECASE)
_SIZE_UNITS = {"b": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12, "pb": 10**15}
_SIZE_UNITS |= {"kib": 1 << 10, "mib": 1 << 20, "gib": 1 << 30, "tib": 1 << 40, "pib": 1 << 50}


def parse_size(text: str) -> int:
    """``1048576``, ``10MB`` (10**6 bytes) or ``2GiB`` (2 * 2**30); a typer parser."""
    match = _SIZE.fullmatch(text) if len(text) < 64 else None
    if match is None:
        raise typer.BadParameter(
            f"{text!r} is not a size: use bytes or a number with B, kB, MB, GB, TB, KiB, MiB, GiB"
        )
    return int(match.group(1)) * _SIZE_UNITS[(match.group(2) or "b").lower()]


def cid_argument(text: str) -> CID:
    """A CID argument; bad text is a usage error (exit 2) naming what was given."""
    try:
        return parse_cid(text, "CID")
    except CIDError as exc:
        raise typer.BadParameter(f"{untrusted(text, 80)!r} is not a CID: {exc}") from exc


def content_argument(text: str) -> tuple[CID, tuple[str, ...]]:
    """``CID`` or ``CID/PATH`` (as ``ipfs cat`` takes one): the CID and the path's segments;
    bad text, or a segment that is empty, ``.`` or ``..``, is a usage error (exit 2)."""
    cid_text, _, path = text.partition("/")
    root = cid_argument(cid_text)
    try:
        return root, split_path(path.rstrip("/"))
    except UnixfsError as exc:
        raise typer.BadParameter(f"{untrusted(text, 80)!r}: {exc}") from exc
