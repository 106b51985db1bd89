"""``robocloud verify RECORD_ID``: check a record's proof against the chain, trusting no service.

The proof comes from the storage node, the AnchorLog address from the ledger's
``/v1/contracts`` (or ``--anchor-log``), and the anchored root, block and transaction from the
chain's JSON-RPC (the ledger's ``/rpc``, or ``--rpc`` for any node the robot trusts). The
check is ``Storage.verified_record``'s, the one a robot runs; this command only finds its
inputs and prints its answer.
"""

from __future__ import annotations

import typer

from robocloud.cli.context import JsonOption, StorageOption, fail
from robocloud.cli.exits import ExitCode
from robocloud.cli.ledger import LedgerOption
from robocloud.cli.output import rows, show, show_json, untrusted
from robocloud.ledger import JsonRpcClient, LedgerService
from robocloud.ledger.client import checksum
from robocloud.proofs import RecordId, RecordIdError
from robocloud.storage import Storage


def verify(
    record_id: str = typer.Argument(..., help="The record's id, <name>-<version>-<index>."),
    storage: str | None = StorageOption,
    ledger_url: str | None = LedgerOption,
    rpc_url: str | None = typer.Option(
        None,
        "--rpc",
        help="An Ethereum JSON-RPC URL to read the anchor from.",
        show_default="the ledger's /rpc",
    ),
    anchor_log: str | None = typer.Option(
        None,
        "--anchor-log",
        help="The AnchorLog address to trust.",
        show_default="the ledger's /v1/contracts",
    ),
    node: str | None = typer.Option(
        None, "--node", help="Accept only anchors of this storage node's address."
    ),
    wait: float = typer.Option(
        0.0,
        "--wait",
        min=0,
        metavar="SECONDS",
        help="Wait this long for a record not anchored yet (a node anchors within seconds).",
    ),
    as_json: bool = JsonOption,
) -> None:
    """Verify a record: its inclusion proofs with SHA-256, its anchor and tx on the chain."""
    try:
        parsed = RecordId.parse(record_id)
    except RecordIdError as exc:
        fail(str(exc), ExitCode.USAGE, "a record id is <name>-<version>-<index>, like imu-1-0")
    if anchor_log is None or rpc_url is None:
        with LedgerService(ledger_url) as service:
            anchor_log = anchor_log or service.contracts().anchor_log
            rpc_url = rpc_url or f"{service.base_url}/rpc"
    with Storage(storage) as client, JsonRpcClient(rpc_url) as rpc:
        proof = client.verified_record(
            str(parsed),
            rpc.request,
            anchor_log=checksum(anchor_log),
            node=checksum(node) if node else None,
            wait_s=wait,
        )
    if as_json:
        show_json({"id": str(parsed), "verified": True, **proof.to_json()})
        return
    show(
        *rows(
            [
                ("record", f"{parsed} verified"),
                (
                    "template",
                    f"{untrusted(proof.template)}: leaf {proof.leaf_index} of {proof.tree_size}",
                ),
                ("epoch", f"{proof.epoch}: TMT root {proof.tmt_root.hex()}"),
                (
                    "anchor",
                    f"{proof.anchor.node} on chain {proof.anchor.chain_id}, tx {proof.anchor.tx}",
                ),
            ]
        )
    )


def register(app: typer.Typer) -> None:
    app.command("verify")(verify)
