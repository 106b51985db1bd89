"""``robocloud keys``: create and inspect the robot's key."""

from __future__ import annotations

from pathlib import Path

import typer

from robocloud.cli.context import JsonOption, KeystoreOption, keystore_path, passphrase
from robocloud.cli.output import rows, show, show_json
from robocloud.identity import Identity

keys = typer.Typer(help="Create and inspect the robot's key (an encrypted Ethereum keystore).")


def _show_key(address: str, path: Path, as_json: bool) -> None:
    if as_json:
        show_json({"address": address, "keystore": str(path)})
    else:
        show(*rows([("address", address), ("keystore", path)]))


@keys.command("new")
def new(keystore: Path | None = KeystoreOption, as_json: bool = JsonOption) -> None:
    """Create a new key, encrypted with a passphrase, and print its address."""
    path = keystore_path(keystore)
    identity = Identity.generate()
    identity.save(path, passphrase(confirm=True))
    _show_key(identity.address, path, as_json)


@keys.command("show")
def show_key(keystore: Path | None = KeystoreOption, as_json: bool = JsonOption) -> None:
    """Print the address of the key (no passphrase needed)."""
    path = keystore_path(keystore)
    _show_key(Identity.keystore_address(path), path, as_json)


def register(app: typer.Typer) -> None:
    app.add_typer(keys, name="keys")
