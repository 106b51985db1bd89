"""``robocloud register``, ``advertise`` and ``robot``: the robot's own ledger transactions.

Every transaction is signed here with the robot's key and sent to the ledger's standard
JSON-RPC; the ledger service only says where the contracts are and runs the dev faucet.
"""

from __future__ import annotations

from pathlib import Path

import httpx
import typer

from robocloud.cid import CID
from robocloud.cli.context import KeystoreOption, console, fail, load_identity
from robocloud.errors import KeystoreError, RobocloudError
from robocloud.identity import Identity, default_keystore_path
from robocloud.ledger import Ledger

LedgerOption = typer.Option(
    None, "--ledger", help="Ledger service URL [default: $ROBOCLOUD_LEDGER_URL or loopback]"
)


def cid_bytes(text: str) -> bytes:
    """The binary form of a CID as it goes on chain; ``0x``-hex of that form is accepted too."""
    try:
        cid = CID.from_bytes(bytes.fromhex(text[2:])) if text.startswith("0x") else CID.decode(text)
    except ValueError as exc:
        raise typer.BadParameter(f"{text!r} is not a CID: {exc}") from exc
    return cid.binary


def did_cid(identity: Identity, chain_id: int) -> bytes:
    """The raw CID of the robot's DID: its metadata until it publishes a description."""
    return CID.from_block(identity.did(chain_id).encode()).binary


def _connect(ledger_url: str | None, identity: Identity | None) -> Ledger:
    try:
        return Ledger.connect(ledger_url, identity)
    except (RobocloudError, httpx.HTTPError) as exc:
        raise fail(f"cannot reach the ledger: {exc}") from exc


def register_robot(
    metadata: str | None = typer.Option(
        None, "--metadata", help="CID of the robot's description [default: CID of its DID]"
    ),
    faucet: bool = typer.Option(True, help="Ask the dev chain's faucet for gas when unfunded"),
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
) -> None:
    """Register this robot in the Registry (funding it from the dev faucet first)."""
    metadata_cid = cid_bytes(metadata) if metadata else None
    identity = load_identity(keystore)
    with _connect(ledger_url, identity) as ledger:
        try:
            if ledger.robot(identity.address).registered:
                console.print(f"robot    {identity.address} is already registered")
                return
            if faucet and ledger.balance() == 0:
                ledger.faucet()
                console.print(f"funded   {ledger.balance()} wei from the faucet")
            receipt = ledger.register(metadata_cid or did_cid(identity, ledger.chain_id))
        except (RobocloudError, httpx.HTTPError) as exc:
            raise fail(str(exc)) from exc
        console.print(f"robot    {identity.address} registered")
        console.print(f"tx       {receipt.tx_hash} (block {receipt.block_number})")


def advertise(
    cid: str = typer.Argument(..., help="CID of the data this robot holds"),
    description: str | None = typer.Option(None, "--description", help="CID of its description"),
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
) -> None:
    """Announce on chain that this robot holds CID; the first advertiser is timestamped."""
    binary = cid_bytes(cid)
    description_binary = cid_bytes(description) if description else b""
    identity = load_identity(keystore)
    with _connect(ledger_url, identity) as ledger:
        try:
            event = ledger.advertise(binary, description_binary)
            summary = ledger.advertisement(binary)
        except (RobocloudError, httpx.HTTPError) as exc:
            raise fail(str(exc)) from exc
    console.print(f"advertised {cid}")
    console.print(f"first      {'yes' if event.first else 'no'}")
    if summary is not None:
        console.print(f"first by   {summary.first_advertiser} at {summary.first_timestamp}")
        console.print(f"count      {summary.count}")
    console.print(f"tx         {event.tx_hash} (block {event.block_number})")


def robot(
    address: str | None = typer.Argument(None, help="Robot address [default: this robot]"),
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
) -> None:
    """Show a robot's Registry record (no passphrase needed)."""
    try:
        target = address or Identity.keystore_address(keystore or default_keystore_path())
    except KeystoreError as exc:
        raise fail(str(exc)) from exc
    with _connect(ledger_url, None) as ledger:
        try:
            record = ledger.robot(target)
        except (RobocloudError, ValueError, httpx.HTTPError) as exc:
            raise fail(str(exc)) from exc
    if not record.registered:
        raise fail(f"{record.address} is not registered")
    state = "active" if record.is_active else "suspended" if record.suspended else "inactive"
    console.print(f"robot      {record.address}")
    console.print(f"state      {state}")
    console.print(f"metadata   0x{record.metadata_cid.hex()}")
    console.print(f"registered {record.registered_at}")


def register(app: typer.Typer) -> None:
    app.command("register")(register_robot)
    app.command("advertise")(advertise)
    app.command("robot")(robot)
