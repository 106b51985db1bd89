"""Calls see the block they name: ``block.number``, ``block.timestamp``, ``block.basefee``
(and ``tx.gasprice``) of that block at ``latest``, a number or a hash; ``pending`` sees the
next block. The same contract on the ledger and on anvil, read the same way on both."""

from __future__ import annotations

from typing import Any

import pytest

from tests.integration.services.ledger.conftest import Pair, call, deploying, mined, result
from tests.rawtx import RawTx
from tests.unit.services.ledger.test_calls import COUNTER

# NUMBER, TIMESTAMP, BASEFEE and GASPRICE as four words: the block context a call sees.
CONTEXT = bytes.fromhex("435f5242602052486040523a60605260805ff3")


def context(url: str, address: str, tag: Any, **fields: Any) -> dict[str, int]:
    answer = result(url, "eth_call", [{"to": address, **fields}, tag])
    words = [int(answer[2 + 64 * i : 66 + 64 * i], 16) for i in range(4)]
    return dict(zip(("number", "timestamp", "basefee", "gasprice"), words, strict=True))


def header(url: str, tag: str) -> dict[str, int]:
    block = result(url, "eth_getBlockByNumber", [tag, False])
    return {
        "number": int(block["number"], 16),
        "timestamp": int(block["timestamp"], 16),
        "basefee": int(block["baseFeePerGas"], 16),
        "hash": block["hash"],
    }


@pytest.fixture(scope="module")
def contracts(pair: Pair) -> tuple[str, str]:
    owner = pair.funded()
    addresses = pair.deploy(owner, deploying(CONTEXT))
    for url in pair.urls:  # two more blocks, so that the deployment block is not the head
        for _ in range(2):
            nonce = int(result(url, "eth_getTransactionCount", [owner.address, "latest"]), 16)
            tx = RawTx(nonce=nonce, max_fee=10**11)
            tx_hash = result(url, "eth_sendRawTransaction", [tx.sign(bytes(owner.account.key))])
            assert mined(url, tx_hash)["status"] == "0x1"
    return addresses


def test_latest_a_number_and_a_hash_run_in_that_blocks_context(
    pair: Pair, contracts: tuple[str, str]
) -> None:
    for url, address in zip(pair.urls, contracts, strict=True):
        latest = header(url, "latest")
        older = header(url, hex(latest["number"] - 2))
        without_hash = {k: v for k, v in latest.items() if k != "hash"}
        assert context(url, address, "latest") == {**without_hash, "gasprice": 0}, url
        by_number = context(url, address, hex(older["number"]))
        assert by_number == {**{k: v for k, v in older.items() if k != "hash"}, "gasprice": 0}
        assert context(url, address, {"blockHash": older["hash"]}) == by_number
        assert context(url, address, {"blockNumber": hex(older["number"])}) == by_number
        assert older["basefee"] != latest["basefee"], "base fees differ between blocks"


def test_pending_sees_the_next_block(pair: Pair, contracts: tuple[str, str]) -> None:
    for url, address in zip(pair.urls, contracts, strict=True):
        latest = header(url, "latest")
        next_base_fee = int(
            result(url, "eth_feeHistory", ["0x1", "latest", []])["baseFeePerGas"][-1], 16
        )
        seen = context(url, address, "pending")
        assert seen["number"] == latest["number"] + 1, url
        assert seen["timestamp"] >= latest["timestamp"]
        assert seen["basefee"] == next_base_fee
        assert seen["gasprice"] == 0


def test_gasprice_is_what_a_mined_transaction_would_pay(
    pair: Pair, contracts: tuple[str, str]
) -> None:
    caller = pair.funded()
    answers = []
    for url, address in zip(pair.urls, contracts, strict=True):
        base_fee = header(url, "latest")["basefee"]
        legacy = context(
            url, address, "latest", **{"from": caller.address, "gasPrice": hex(5 * 10**9)}
        )
        dynamic = context(
            url,
            address,
            "latest",
            **{
                "from": caller.address,
                "maxFeePerGas": hex(5 * 10**9),
                "maxPriorityFeePerGas": hex(10**9),
            },
        )
        assert legacy["gasprice"] == 5 * 10**9
        assert dynamic["gasprice"] == min(5 * 10**9, 10**9 + base_fee)
        answers.append((legacy["gasprice"], dynamic["gasprice"] - base_fee))
    assert answers[0] == answers[1]


def test_a_priced_call_its_sender_cannot_afford_is_refused_on_both(
    pair: Pair, contracts: tuple[str, str]
) -> None:
    for url, address in zip(pair.urls, contracts, strict=True):
        error = call(url, "eth_call", [{"to": address, "gasPrice": hex(10**9)}, "latest"])["error"]
        assert error["message"].lower().startswith("insufficient funds for gas * price + value")


def test_calls_leave_nothing_behind_and_see_each_new_head(pair: Pair) -> None:
    """The ledger reuses a state for calls at the same block (anvil need not): a call that
    writes storage and transient storage changes nothing the next call or block sees."""
    owner = pair.funded()
    addresses = pair.deploy(owner, deploying(COUNTER))
    for url, address in zip(pair.urls, addresses, strict=True):
        deployed = result(url, "eth_blockNumber", [])
        assert [counts(url, address, "latest") for _ in range(3)] == [(0, 0)] * 3, url
        nonce = int(result(url, "eth_getTransactionCount", [owner.address, "latest"]), 16)
        tx = RawTx(nonce=nonce, to=bytes.fromhex(address[2:]), gas=100_000, max_fee=10**11)
        tx_hash = result(url, "eth_sendRawTransaction", [tx.sign(bytes(owner.account.key))])
        assert mined(url, tx_hash)["status"] == "0x1"
        assert counts(url, address, "latest") == (1, 0), url
        assert counts(url, address, deployed) == (0, 0), url
        assert counts(url, address, "latest") == (1, 0), url


def counts(url: str, address: str, tag: str) -> tuple[int, int]:
    answer = result(url, "eth_call", [{"to": address}, tag])
    return int(answer[2:66], 16), int(answer[66:130], 16)
