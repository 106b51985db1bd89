"""``robocloud admin ...``: administering the Registry, as its admin or as a registrar.

The admin is whoever deployed the Registry: for the embedded development chain, the ledger
service's operator key (``data/ledger/keys/admin.json``, its passphrase in
``ROBOCLOUD_LEDGER_ADMIN_PASSPHRASE`` or ``data/ledger/operator.secret``); pass that keystore
with ``--keystore``. A robot the admin granted the ``registrar`` role approves and rejects
with its own key. Every command signs its transaction locally, as a robot's would be.
"""

from __future__ import annotations

from pathlib import Path

import typer

from robocloud.cli.context import JsonOption, KeystoreOption, load_identity
from robocloud.cli.ledger import LedgerOption, robot_address
from robocloud.cli.output import iso8601, rows, show, show_json
from robocloud.ledger import Ledger, LedgerService, RegistrationMode, Role
from robocloud.ledger.transactions import Receipt

admin_app = typer.Typer(
    name="admin",
    help=(
        "Administer the Registry: approve or reject registrations, grant and revoke roles, "
        "suspend robots, set the registration mode."
    ),
    no_args_is_help=True,
)

AddressArgument = typer.Argument(
    ..., help="The robot's address.", metavar="ADDRESS", callback=robot_address
)


def _report(action: str, address: str, receipt: Receipt, as_json: bool) -> None:
    if as_json:
        show_json(
            {
                "address": address,
                "action": action,
                "tx": receipt.tx_hash,
                "block": receipt.block_number,
            }
        )
    else:
        show(
            *rows(
                [
                    ("robot", f"{address} {action}"),
                    ("tx", f"{receipt.tx_hash} (block {receipt.block_number})"),
                ]
            )
        )


@admin_app.command("approve")
def approve(
    address: str = AddressArgument,
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
    as_json: bool = JsonOption,
) -> None:
    """Admit a robot whose registration awaits approval (admin or registrar)."""
    _decide(address, approved=True, keystore=keystore, ledger_url=ledger_url, as_json=as_json)


@admin_app.command("reject")
def reject(
    address: str = AddressArgument,
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
    as_json: bool = JsonOption,
) -> None:
    """Refuse a pending registration; the robot may ask again (admin or registrar)."""
    _decide(address, approved=False, keystore=keystore, ledger_url=ledger_url, as_json=as_json)


def _decide(
    address: str, *, approved: bool, keystore: Path | None, ledger_url: str | None, as_json: bool
) -> None:
    with Ledger.connect(ledger_url, load_identity(keystore)) as ledger:
        receipt = ledger.approve(address) if approved else ledger.reject(address)
    _report("approved" if approved else "rejected", address, receipt, as_json)


@admin_app.command("pending")
def pending(
    limit: int = typer.Option(100, min=1, max=1000, help="At most this many, oldest first."),
    ledger_url: str | None = LedgerOption,
    as_json: bool = JsonOption,
) -> None:
    """List the registrations awaiting approval (from the ledger's index; needs no key)."""
    with LedgerService(ledger_url) as service:
        waiting = service.pending(limit)
    if as_json:
        show_json(
            [
                {
                    "address": robot.address,
                    "metadata": robot.metadata_cid or robot.metadata_hex,
                    "requested_at": iso8601(robot.registered_at),
                }
                for robot in waiting
            ]
        )
        return
    if not waiting:
        show("no registration awaits approval")
        return
    show(*rows((robot.address, f"asked {iso8601(robot.registered_at)}") for robot in waiting))


@admin_app.command("grant")
def grant(
    address: str = AddressArgument,
    role: Role = typer.Argument(..., help="The role to grant.", metavar="ROLE"),
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
    as_json: bool = JsonOption,
) -> None:
    """Grant a registered robot a role: storage_node, reviewer, aggregator or registrar (admin)."""
    with Ledger.connect(ledger_url, load_identity(keystore)) as ledger:
        receipt = ledger.grant_role(address, role)
    _report(f"granted {role.value}", address, receipt, as_json)


@admin_app.command("revoke")
def revoke(
    address: str = AddressArgument,
    role: Role = typer.Argument(..., help="The role to revoke.", metavar="ROLE"),
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
    as_json: bool = JsonOption,
) -> None:
    """Take a role back: a registrar revoked decides no more registrations (admin)."""
    with Ledger.connect(ledger_url, load_identity(keystore)) as ledger:
        receipt = ledger.revoke_role(address, role)
    _report(f"revoked {role.value}", address, receipt, as_json)


@admin_app.command("suspend")
def suspend(
    address: str = AddressArgument,
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
    as_json: bool = JsonOption,
) -> None:
    """Suspend a registered robot: services refuse its writes, it advertises nothing (admin)."""
    _suspension(address, True, keystore=keystore, ledger_url=ledger_url, as_json=as_json)


@admin_app.command("reinstate")
def reinstate(
    address: str = AddressArgument,
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
    as_json: bool = JsonOption,
) -> None:
    """Lift a robot's suspension (admin)."""
    _suspension(address, False, keystore=keystore, ledger_url=ledger_url, as_json=as_json)


def _suspension(
    address: str, suspended: bool, *, keystore: Path | None, ledger_url: str | None, as_json: bool
) -> None:
    with Ledger.connect(ledger_url, load_identity(keystore)) as ledger:
        receipt = ledger.set_suspended(address, suspended)
    _report("suspended" if suspended else "reinstated", address, receipt, as_json)


@admin_app.command("mode")
def mode(
    new_mode: str | None = typer.Argument(
        None,
        help="open or approved; without it, print the mode in force.",
        metavar="[open|approved]",
        show_default=False,
    ),
    keystore: Path | None = KeystoreOption,
    ledger_url: str | None = LedgerOption,
    as_json: bool = JsonOption,
) -> None:
    """Show or set the Registry's registration mode (setting it: admin).

    A ledger holding the admin key applies its ROBOCLOUD_LEDGER_REGISTRATION_MODE again at its
    next start; change that setting to make a switch last.
    """
    if new_mode is None:
        with Ledger.connect(ledger_url, None) as ledger:
            current = ledger.registration_mode()
        if as_json:
            show_json({"mode": current.name.lower()})
        else:
            show(f"mode     {current.name.lower()}")
        return
    if new_mode not in ("open", "approved"):
        raise typer.BadParameter(f"{new_mode!r}: expected open or approved", param_hint="MODE")
    target = RegistrationMode[new_mode.upper()]
    with Ledger.connect(ledger_url, load_identity(keystore)) as ledger:
        receipt = ledger.set_registration_mode(target)
    if as_json:
        show_json({"mode": new_mode, "tx": receipt.tx_hash, "block": receipt.block_number})
    else:
        show(
            *rows([("mode", new_mode), ("tx", f"{receipt.tx_hash} (block {receipt.block_number})")])
        )


def register(app: typer.Typer) -> None:
    app.add_typer(admin_app)
