"""``robocloud register``, ``advertise`` and ``robot``: the robot's own ledger transactions.

Every transaction is signed here with the robot's key and sent to the ledger's standard
JSON-RPC; the ledger service only says where the contracts are and runs the dev faucet.
Commands that administer the Registry (``robocloud admin ...``) belong in their own module.
"""

from __future__ import annotations

from pathlib import Path

import typer

from robocloud.cid import CID, CIDError
from robocloud.cli.context import (
    JsonOption,
    KeystoreOption,
    cid_argument,
    fail,
    keystore_path,
    load_identity,
)
from robocloud.cli.exits import ExitCode
from robocloud.cli.output import iso8601, rows, show, show_json, untrusted
from robocloud.identity import Identity
from robocloud.ledger import AddressError, Ledger
from robocloud.ledger.client import checksum

LedgerOption = typer.Option(
    None,
    "--ledger",
    help="URL of the ledger service.",
    show_default="$ROBOCLOUD_LEDGER_URL, else http://127.0.0.1:8545",
)


def cid_bytes(text: str) -> bytes:
    """The binary form of a CID as it goes on chain; ``0x``-hex of that form is accepted too."""
    if not text.startswith("0x"):
        return cid_argument(text).binary
    try:
        return CID.from_bytes(bytes.fromhex(text[2:])).binary
    except (CIDError, ValueError) as exc:
        raise typer.BadParameter(f"{untrusted(text, 80)!r} is not a CID: {exc}") from exc


def cid_text(binary: bytes) -> str:
    """A CID read from the chain as text, or its hex when the bytes are not a CID."""
    try:
        return str(CID.from_bytes(binary))
    except (CIDError, ValueError):
        return "0x" + binary.hex()


def did_cid(identity: Identity, chain_id: int) -> bytes:
    """The raw CID of the robot's DID: its metadata until it publishes a description."""
    return CID.from_block(identity.did(chain_id).encode()).binary


def register_robot(
    metadata: str | None = typer.Option(
        None,
        "--metadata",
        help="CID of the robot's description.",
        show_default="the CID of the robot's DID",
    ),
    faucet: bool = typer.Option(True, help="Ask the dev chain's faucet for gas when unfunded."),
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
    as_json: bool = JsonOption,
) -> None:
    """Register this robot in the Registry (funding it from the dev faucet first)."""
    metadata_cid = cid_bytes(metadata) if metadata else None
    identity = load_identity(keystore)
    with Ledger.connect(ledger_url, identity) as ledger:
        known = ledger.robot(identity.address).registered or ledger.is_pending(identity.address)
        if known:
            _show_registration(identity.address, ledger.is_pending(identity.address), as_json)
            return
        funded = None
        if faucet and ledger.balance() == 0:
            ledger.faucet()
            funded = ledger.balance()
        receipt = ledger.register(metadata_cid or did_cid(identity, ledger.chain_id))
        pending = ledger.is_pending(identity.address)
    if as_json:
        show_json(
            {
                "address": identity.address,
                "registered": not pending,
                "pending": pending,
                "new": True,
                "funded_wei": funded,
                "tx": receipt.tx_hash,
                "block": receipt.block_number,
            }
        )
        return
    outcome = (
        "asked to register; awaits approval by the admin or a registrar"
        if pending
        else "registered"
    )
    lines = [("robot", f"{identity.address} {outcome}")]
    if funded is not None:
        lines.insert(0, ("funded", f"{funded} wei from the faucet"))
    lines.append(("tx", f"{receipt.tx_hash} (block {receipt.block_number})"))
    show(*rows(lines))


def _show_registration(address: str, pending: bool, as_json: bool) -> None:
    if as_json:
        show_json({"address": address, "registered": not pending, "pending": pending, "new": False})
    elif pending:
        show(f"robot    {address} already asked to register; awaits approval")
    else:
        show(f"robot    {address} is already registered")


def advertise(
    cid: str = typer.Argument(
        ..., help="CID of the data this robot holds.", metavar="CID", show_default=False
    ),
    description: str | None = typer.Option(
        None, "--description", help="CID of its description.", show_default="none"
    ),
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
    as_json: bool = JsonOption,
) -> None:
    """Announce on chain that this robot holds CID; the first advertiser is timestamped."""
    binary = cid_bytes(cid)
    description_binary = cid_bytes(description) if description else b""
    identity = load_identity(keystore)
    with Ledger.connect(ledger_url, identity) as ledger:
        event = ledger.advertise(binary, description_binary)
        summary = ledger.advertisement(binary)
    first_by = summary.first_advertiser if summary is not None else None
    first_at = iso8601(summary.first_timestamp) if summary is not None else None
    count = summary.count if summary is not None else None
    if as_json:
        show_json(
            {
                "cid": cid_text(binary),
                "first": event.first,
                "first_advertiser": first_by,
                "first_time": first_at,
                "count": count,
                "tx": event.tx_hash,
                "block": event.block_number,
            }
        )
        return
    lines: list[tuple[str, object]] = [
        ("advertised", cid_text(binary)),
        ("first", "yes" if event.first else "no"),
    ]
    if summary is not None:
        lines += [("first by", f"{first_by} at {first_at}"), ("count", count)]
    lines.append(("tx", f"{event.tx_hash} (block {event.block_number})"))
    show(*rows(lines))


def robot_address(value: str | None) -> str | None:
    if value is None:
        return None
    try:
        return checksum(value)
    except AddressError as exc:
        raise typer.BadParameter(str(exc)) from exc


def robot(
    address: str | None = typer.Argument(
        None,
        help="The robot's address.",
        metavar="ADDRESS",
        show_default="this robot's (read from the keystore, no passphrase needed)",
        callback=robot_address,
    ),
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
    as_json: bool = JsonOption,
) -> None:
    """Show a robot's Registry record, read from the chain."""
    target = address or Identity.keystore_address(keystore_path(keystore))
    with Ledger.connect(ledger_url, None) as ledger:
        record = ledger.robot(target)
        pending = not record.registered and ledger.is_pending(target)
    if not record.registered and not pending:
        fail(
            f"{record.address} is not registered",
            ExitCode.ERROR,
            "`robocloud register` registers this robot",
        )
    state = (
        "pending approval"
        if pending
        else "active"
        if record.is_active
        else "suspended"
        if record.suspended
        else "inactive"
    )
    registered = iso8601(record.registered_at)
    if as_json:
        show_json(
            {
                "address": record.address,
                "state": state,
                "metadata": cid_text(record.metadata_cid),
                "registered_at": registered,
            }
        )
        return
    show(
        *rows(
            [
                ("robot", record.address),
                ("state", state),
                ("metadata", cid_text(record.metadata_cid)),
                ("registered", registered),
            ]
        )
    )


def register(app: typer.Typer) -> None:
    app.command("register")(register_robot)
    app.command("advertise")(advertise)
    app.command("robot")(robot)
