"""``robocloud keys``: create and inspect the robot's key."""

from __future__ import annotations

from pathlib import Path

import typer

from robocloud.cli.context import KeystoreOption, console, fail, passphrase
from robocloud.errors import KeystoreError
from robocloud.identity import Identity, default_keystore_path

keys = typer.Typer(help="Create and inspect the robot's key (an encrypted Ethereum keystore).")


@keys.command("new")
def new(keystore: Path | None = KeystoreOption) -> None:
    """Create a new key, encrypted with a passphrase, and print its address."""
    path = keystore or default_keystore_path()
    identity = Identity.generate()
    try:
        identity.save(path, passphrase(confirm=True))
    except KeystoreError as exc:
        raise fail(str(exc)) from exc
    console.print(f"address  {identity.address}")
    console.print(f"keystore {path}")


@keys.command("show")
def show(keystore: Path | None = KeystoreOption) -> None:
    """Print the address of the key (no passphrase needed)."""
    path = keystore or default_keystore_path()
    try:
        address = Identity.keystore_address(path)
    except KeystoreError as exc:
        raise fail(str(exc)) from exc
    console.print(f"address  {address}")
    console.print(f"keystore {path}")


def register(app: typer.Typer) -> None:
    app.add_typer(keys, name="keys")
