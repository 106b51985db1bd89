"""A restarted or killed ledger comes back with the same head hash and every acknowledged
transaction, its contracts at the same addresses and its index intact."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from robocloud.identity import Identity
from robocloud.ledger import Ledger, Role
from tests.integration.services.ledger.conftest import (
    METADATA,
    admin_of,
    faucet,
    head,
    rpc,
    start_ledger,
)


@pytest.mark.parametrize("kill", [False, True], ids=["restart", "kill-9"])
def test_head_hash_and_acknowledged_transactions_survive(tmp_path: Path, kill: bool) -> None:
    process = start_ledger(tmp_path / "data")
    try:
        contracts = httpx.get(f"{process.url}/v1/contracts").json()
        robots = [Identity.generate() for _ in range(3)]
        acknowledged: list[str] = []
        for identity in robots:
            with Ledger.connect(process.url, identity, receipt_timeout_s=10) as robot:
                robot.faucet()
                acknowledged.append(robot.register(METADATA).tx_hash)
        before = head(process.url)
        process.stop(kill=kill)
        process.start()
        assert head(process.url) == before
        assert httpx.get(f"{process.url}/v1/contracts").json() == contracts
        for tx_hash in acknowledged:
            receipt = rpc(process.url, "eth_getTransactionReceipt", [tx_hash])["result"]
            assert receipt["status"] == "0x1"
        for identity in robots:
            record = httpx.get(f"{process.url}/v1/robots/{identity.address}")
            assert record.status_code == 200
            again = faucet(process.url, identity)
            assert again.status_code == 429, "a restart must not reset the faucet's interval"
            assert again.json()["error"]["code"] == "faucet_rate_limited"
        with Ledger.connect(process.url, robots[0], receipt_timeout_s=10) as robot:
            robot.advertise(b"\x01\x55\x12\x20" + bytes(32))
        assert head(process.url)["number"] == before["number"] + 1
    finally:
        process.stop()


def test_an_anchor_past_int64_is_indexed_and_the_ledger_restarts(tmp_path: Path) -> None:
    """AnchorLog takes any uint64 epoch and record count. Epoch 2^63 made the index fail
    that block (SQLite integers are signed), so every later block stayed unindexed (robots
    registered after it were 404) and the ledger no longer started (its catch-up failed)."""
    process = start_ledger(tmp_path / "data")
    try:
        with (
            Ledger.connect(process.url, admin_of(process), receipt_timeout_s=10) as admin,
            Ledger.connect(process.url, Identity.generate(), receipt_timeout_s=10) as node,
        ):
            node.faucet()
            node.register(METADATA)
            assert node.identity is not None
            admin.grant_role(node.identity.address, Role.STORAGE_NODE)
            huge = node.anchor(2**63, b"\x01" * 32, 2**64 - 1)
            last = node.anchor(2**64 - 1, b"\x02" * 32, 2**63)
        later = Identity.generate()
        with Ledger.connect(process.url, later, receipt_timeout_s=10) as robot:
            robot.faucet()
            robot.register(METADATA)

        def check() -> None:
            rows = httpx.get(f"{process.url}/v1/anchors", params={"node": huge.node}).json()
            assert [(r["epoch"], r["record_count"], r["tx"]) for r in rows["anchors"]] == [
                (2**63, 2**64 - 1, huge.tx_hash),
                (2**64 - 1, 2**63, last.tx_hash),
            ]
            one = httpx.get(f"{process.url}/v1/anchors", params={"epoch": 2**64 - 1}).json()
            assert [r["tx"] for r in one["anchors"]] == [last.tx_hash]
            assert httpx.get(f"{process.url}/v1/robots/{later.address}").status_code == 200

        check()
        process.stop()
        process.start()
        check()
    finally:
        process.stop()
