"""What every command needs: the robot's identity and console output."""

from __future__ import annotations

import os
from pathlib import Path

import typer
from rich.console import Console

from robocloud.errors import KeystoreError
from robocloud.identity import PASSPHRASE_ENV, Identity, default_keystore_path

console = Console()
errors = Console(stderr=True)

KeystoreOption = typer.Option(
    None, "--keystore", "-k", help="Keystore file [default: $ROBOCLOUD_KEYSTORE or ~/.robocloud]"
)


def passphrase(*, confirm: bool = False) -> str:
    """``$ROBOCLOUD_PASSPHRASE`` for scripts and robots, else an interactive prompt."""
    from_env = os.environ.get(PASSPHRASE_ENV)
    if from_env:
        return from_env
    return str(typer.prompt("Keystore passphrase", hide_input=True, confirmation_prompt=confirm))


def load_identity(keystore: Path | None) -> Identity:
    path = keystore or default_keystore_path()
    try:
        return Identity.load(path, passphrase())
    except KeystoreError as exc:
        raise fail(str(exc)) from exc


def fail(message: str, code: int = 1) -> typer.Exit:
    """Print an error and exit non-zero (typed as returning so callers can ``raise fail(...)``)."""
    errors.print(f"[bold red]error:[/] {message}")
    raise typer.Exit(code)
