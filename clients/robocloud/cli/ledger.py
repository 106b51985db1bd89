"""``robocloud register``, ``advertise`` and ``robot``: the robot's own ledger transactions.

Every transaction is signed here with the robot's key and sent to the ledger's standard
JSON-RPC; the ledger service only says where the contracts are and runs the dev faucet.
"""

from __future__ import annotations

import base64
import hashlib
from pathlib import Path

import httpx
import typer

from robocloud.cli.context import KeystoreOption, console, fail, load_identity
from robocloud.errors import KeystoreError, RobocloudError
from robocloud.identity import Identity, default_keystore_path
from robocloud.ledger import Ledger

LedgerOption = typer.Option(
    None, "--ledger", help="Ledger service URL [default: $ROBOCLOUD_LEDGER_URL or loopback]"
)

_BASE58 = "123456789ABCDEFGHJKLMNPQRSTUVWXYZabcdefghijkmnopqrstuvwxyz"
RAW_CODEC = 0x55
SHA2_256 = 0x12


def _base58_decode(text: str) -> bytes:
    number = 0
    for char in text:
        digit = _BASE58.find(char)
        if digit < 0:
            raise ValueError(f"{char!r} is not a base58btc digit")
        number = number * 58 + digit
    body = number.to_bytes((number.bit_length() + 7) // 8, "big")
    return b"\x00" * (len(text) - len(text.lstrip("1"))) + body


def cid_bytes(text: str) -> bytes:
    """The binary form of a CID as it goes on chain.

    Accepts CIDv0 (``Qm...``), CIDv1 in base32 (``b...``) or base58btc (``z...``) multibase,
    and ``0x``-hex of the binary form.
    """
    try:
        if text.startswith("0x"):
            binary = bytes.fromhex(text[2:])
        elif text.startswith("Qm") and len(text) == 46:
            binary = _base58_decode(text)
        elif text.startswith("b"):
            body = text[1:].upper()
            binary = base64.b32decode(body + "=" * (-len(body) % 8))
        elif text.startswith("z"):
            binary = _base58_decode(text[1:])
        else:
            raise ValueError("unknown multibase prefix")
    except ValueError as exc:
        raise typer.BadParameter(f"{text!r} is not a CID: {exc}") from exc
    if not binary or not (binary[0] == 0x01 or binary[:2] == bytes([SHA2_256, 32])):
        raise typer.BadParameter(f"{text!r} is not a CID: neither CIDv1 nor CIDv0")
    return binary


def did_cid(identity: Identity, chain_id: int) -> bytes:
    """CIDv1 (raw, SHA-256) of the robot's DID: its metadata until it publishes a description."""
    digest = hashlib.sha256(identity.did(chain_id).encode()).digest()
    return bytes([0x01, RAW_CODEC, SHA2_256, len(digest)]) + digest


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
