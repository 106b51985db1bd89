"""A restarted or killed ledger comes back with the same head hash and every acknowledged
transaction, its contracts at the same addresses and its index intact."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from robocloud.identity import Identity
from robocloud.ledger import Ledger
from tests.integration.services.ledger.conftest import METADATA, faucet, head, rpc, start_ledger


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
