"""Transactions with a nonce gap wait until it closes, as on anvil: ten consecutive nonces
sent out of order are all mined; the queue is bounded per sender, in total and in time."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pytest

from robocloud.identity import Identity
from tests.integration.services.ledger.conftest import (
    Pair,
    call,
    faucet,
    head,
    mined,
    result,
    start_ledger,
)
from tests.procs import ServiceProcess
from tests.rawtx import RawTx

ORDER = (3, 7, 1, 9, 0, 5, 2, 8, 6, 4)


def transfer(identity: Identity, nonce: int, **fields: Any) -> str:
    tx = RawTx(nonce=nonce, **{"max_fee": 10**11, **fields})
    return tx.sign(bytes(identity.account.key))


def test_ten_nonces_out_of_order_are_all_mined_on_both(pair: Pair) -> None:
    sender = pair.funded()
    for url in pair.urls:
        hashes: dict[int, str] = {}
        for nonce in ORDER:
            hashes[nonce] = result(url, "eth_sendRawTransaction", [transfer(sender, nonce)])
            if nonce == 3:
                assert result(url, "eth_getTransactionReceipt", [hashes[3]]) is None, url
        receipts = [mined(url, hashes[n]) for n in range(10)]
        assert all(r["status"] == "0x1" for r in receipts), url
        numbers = [int(r["blockNumber"], 16) for r in receipts]
        assert numbers == sorted(numbers), "mined in nonce order"
        assert result(url, "eth_getTransactionCount", [sender.address, "latest"]) == "0xa"


def test_a_waiting_transaction_is_found_by_hash_in_no_block_on_both(pair: Pair) -> None:
    sender = pair.funded()
    answers = []
    for url in pair.urls:
        waiting = result(url, "eth_sendRawTransaction", [transfer(sender, 1, value=7)])
        found = result(url, "eth_getTransactionByHash", [waiting])
        assert found is not None, url
        answers.append(found)
        next_base_fee = int(
            result(url, "eth_feeHistory", ["0x1", "latest", []])["baseFeePerGas"][-1], 16
        )
        tip = int(found["maxPriorityFeePerGas"], 16)
        assert int(found["gasPrice"], 16) == next_base_fee + tip, url
        result(url, "eth_sendRawTransaction", [transfer(sender, 0)])
        receipt = mined(url, waiting)
        found = result(url, "eth_getTransactionByHash", [waiting])
        assert found["blockNumber"] == receipt["blockNumber"], url
    ours, anvil = answers
    keys = ("hash", "nonce", "from", "to", "value", "blockHash", "blockNumber", "maxFeePerGas")
    assert {key: ours[key] for key in keys} == {key: anvil[key] for key in keys}
    assert (ours["blockHash"], ours["blockNumber"], ours["transactionIndex"]) == (None, None, None)


def test_a_waiting_transaction_is_replaced_only_for_a_higher_price_on_both(pair: Pair) -> None:
    sender = pair.funded()
    for url in pair.urls:
        first = transfer(sender, 1, max_priority_fee=10**9)
        result(url, "eth_sendRawTransaction", [first])
        assert call(url, "eth_sendRawTransaction", [first])["error"]["message"].lower() in (
            "already known",
            "transaction already imported",
        )
        cheap = transfer(sender, 1, max_priority_fee=10**9 + 1, value=1)
        error = call(url, "eth_sendRawTransaction", [cheap])["error"]
        assert "underpriced" in error["message"], (url, error)
        replacement = transfer(sender, 1, max_priority_fee=2 * 10**9, max_fee=2 * 10**11)
        replaced = result(url, "eth_sendRawTransaction", [replacement])
        result(url, "eth_sendRawTransaction", [transfer(sender, 0)])
        receipt = mined(url, replaced)
        assert receipt is not None
        assert receipt["status"] == "0x1"
    own = call(pair.ledger, "eth_sendRawTransaction", [transfer(sender, 5)])
    assert "result" in own


@pytest.fixture(scope="module")
def small_pool(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    process = start_ledger(
        tmp_path_factory.mktemp("pool") / "data",
        {
            "ROBOCLOUD_LEDGER_POOL_MAX_PER_SENDER": "3",
            "ROBOCLOUD_LEDGER_POOL_MAX_TOTAL": "5",
            "ROBOCLOUD_LEDGER_POOL_TIMEOUT_S": "3600",
        },
    )
    try:
        yield process
    finally:
        process.stop()


def funded(process: ServiceProcess) -> Identity:
    identity = Identity.generate()
    assert faucet(process.url, identity).status_code == 200
    return identity


def test_the_queue_is_bounded_per_sender_and_in_total(small_pool: ServiceProcess) -> None:
    url = f"{small_pool.url}/rpc"
    first, second, third = funded(small_pool), funded(small_pool), funded(small_pool)
    before = head(small_pool.url)
    queued = [result(url, "eth_sendRawTransaction", [transfer(first, n)]) for n in (1, 2, 3)]
    error = call(url, "eth_sendRawTransaction", [transfer(first, 4)])["error"]
    assert error == {
        "code": -32000,
        "message": f"txpool is full: address {first.address.lower()} has 3 transactions "
        "waiting for a nonce gap to close (limit 3)",
    }
    for nonce in (1, 2):
        result(url, "eth_sendRawTransaction", [transfer(second, nonce)])
    error = call(url, "eth_sendRawTransaction", [transfer(third, 1)])["error"]
    assert error == {
        "code": -32000,
        "message": "txpool is full: 5 transactions waiting (limit 5)",
    }
    assert head(small_pool.url) == before, "nothing waiting was mined"
    result(url, "eth_sendRawTransaction", [transfer(first, 0)])
    mined(url, queued[-1])
    assert result(url, "eth_getTransactionCount", [first.address, "latest"]) == "0x4"
    result(url, "eth_sendRawTransaction", [transfer(third, 1)])  # room again


def test_a_waiting_transaction_that_became_invalid_is_dropped(small_pool: ServiceProcess) -> None:
    """It was affordable when queued; the transaction closing the gap spends the balance."""
    url = f"{small_pool.url}/rpc"
    sender = funded(small_pool)
    balance = int(result(url, "eth_getBalance", [sender.address, "latest"]), 16)
    waiting = result(url, "eth_sendRawTransaction", [transfer(sender, 1, value=balance // 2)])
    spend = transfer(sender, 0, value=balance - 21_000 * 10**11)
    result(url, "eth_sendRawTransaction", [spend])
    deadline = time.monotonic() + 10
    while result(url, "eth_getTransactionByHash", [waiting]) is not None:
        assert time.monotonic() < deadline, "the unaffordable transaction still waits"
        time.sleep(0.02)
    assert result(url, "eth_getTransactionCount", [sender.address, "latest"]) == "0x1"
    assert result(url, "eth_getTransactionReceipt", [waiting]) is None


def test_waiting_transactions_expire(tmp_path_factory: pytest.TempPathFactory) -> None:
    process = start_ledger(
        tmp_path_factory.mktemp("expiry") / "data", {"ROBOCLOUD_LEDGER_POOL_TIMEOUT_S": "0.5"}
    )
    try:
        url = f"{process.url}/rpc"
        sender = funded(process)
        late = result(url, "eth_sendRawTransaction", [transfer(sender, 1)])
        time.sleep(1.0)  # past the timeout: however slow the machine, it has expired
        result(url, "eth_sendRawTransaction", [transfer(sender, 0)])
        assert result(url, "eth_getTransactionByHash", [late]) is None, "expired, not mined"
        assert result(url, "eth_getTransactionReceipt", [late]) is None
        assert result(url, "eth_getTransactionCount", [sender.address, "latest"]) == "0x1"
    finally:
        process.stop()
