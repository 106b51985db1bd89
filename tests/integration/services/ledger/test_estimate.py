"""eth_estimateGas within 1 % above the least gas that succeeds, as geth's binary search.

The least gas is found independently: a bisection with ``eth_call`` at every gas value
(a call with too little gas fails), then checked by mining transactions with exactly the
estimate (succeeds) on the ledger. anvil answers the same requests for comparison.
"""

from __future__ import annotations

from typing import Any

import pytest

from tests.integration.services.ledger.conftest import Pair, call, deploying, mined, result
from tests.rawtx import RawTx

# Calls itself n times (the first word of calldata) and returns 1 from the deepest call: the
# 63/64 rule keeps back gas at every level, so the least gas is above what the call uses.
RECURSE_RUNTIME = bytes.fromhex(
    "60003580156027576001900360005260206000602060006000305af1503d600060003e3d6000f3"
    "5b600160005260206000f3"
)
# Writes a fresh storage slot (22,100 gas) then clears it (a refund): refunds make the gas
# used less than the gas needed.
STORE_AND_CLEAR = bytes.fromhex("6001600055600060005500")


def least_gas(url: str, request: dict[str, Any]) -> int:
    """The least gas with which ``eth_call`` does what it does with all the gas it wants
    (succeeds, with the same output), by exact bisection.

    "Succeeds" alone is not enough: the recursion below succeeds with little gas too, its
    nested calls failing quietly, and no node's estimate aims at that (geth's reasoning:
    the unconstrained run's gas bounds the answer from below).
    """
    low, high = 20_999, 1_000_000
    unconstrained = call(url, "eth_call", [{**request, "gas": hex(high)}, "latest"])
    assert "result" in unconstrained, unconstrained
    while low + 1 < high:
        middle = (low + high) // 2
        answer = call(url, "eth_call", [{**request, "gas": hex(middle)}, "latest"])
        if answer.get("result") != unconstrained["result"]:
            low = middle
        else:
            high = middle
    return high


@pytest.fixture(scope="module")
def deployed(pair: Pair) -> dict[str, tuple[str, str]]:
    owner = pair.funded()
    return {
        "recurse": pair.deploy(owner, deploying(RECURSE_RUNTIME)),
        "store": pair.deploy(owner, deploying(STORE_AND_CLEAR)),
    }


CASES = {
    "transfer": (None, b""),
    "recurse-1": ("recurse", (1).to_bytes(32, "big")),
    "recurse-8": ("recurse", (8).to_bytes(32, "big")),
    "store-and-clear": ("store", b""),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_estimate_is_within_one_percent_of_the_least_gas(
    pair: Pair, deployed: dict[str, tuple[str, str]], case: str
) -> None:
    contract, data = CASES[case]
    sender = pair.funded()
    estimates = []
    for side, url in enumerate(pair.urls):
        to = deployed[contract][side] if contract else "0x" + "22" * 20
        request = {"from": sender.address, "to": to, "data": "0x" + data.hex()}
        estimate = int(result(url, "eth_estimateGas", [request, "latest"]), 16)
        succeeds = call(url, "eth_call", [{**request, "gas": hex(estimate)}, "latest"])
        assert "result" in succeeds, (url, succeeds)
        estimates.append((estimate, least_gas(url, request)))
    (ours, least), (theirs, node_least) = estimates
    assert least == node_least, "both chains execute the same code the same way"
    assert least <= ours <= least * 1.01, (ours, least)
    assert theirs <= least * 1.01, "anvil aims at least as low (it accepts quiet failures)"


def test_a_transaction_with_the_estimate_succeeds(
    pair: Pair, deployed: dict[str, tuple[str, str]]
) -> None:
    sender = pair.funded()
    to = deployed["recurse"][0]
    data = (8).to_bytes(32, "big")
    request = {"from": sender.address, "to": to, "data": "0x" + data.hex()}
    estimate = int(result(pair.ledger, "eth_estimateGas", [request, "latest"]), 16)
    tx = RawTx(to=bytes.fromhex(to[2:]), data=data, gas=estimate, max_fee=10**11)
    tx_hash = result(pair.ledger, "eth_sendRawTransaction", [tx.sign(bytes(sender.account.key))])
    assert mined(pair.ledger, tx_hash)["status"] == "0x1"


def test_a_call_that_fails_with_all_the_gas_is_refused_as_geth_does(pair: Pair) -> None:
    """An infinite loop needs more gas than any allowance: not a revert."""
    owner = pair.funded()
    ours, theirs = pair.deploy(owner, deploying(bytes.fromhex("5b600056")))
    mine = call(pair.ledger, "eth_estimateGas", [{"to": ours, "gas": hex(100_000)}])["error"]
    node = call(pair.anvil, "eth_estimateGas", [{"to": theirs, "gas": hex(100_000)}])["error"]
    assert mine == {"code": -32000, "message": "gas required exceeds allowance (100000)"}
    assert "gas required exceeds allowance" in node["message"].lower()


def test_an_estimate_is_capped_by_what_the_sender_can_pay(pair: Pair) -> None:
    """geth searches no higher than the sender's balance buys (anvil 1.7.1 ignores it)."""
    poor = pair.funded()
    balance = int(result(pair.ledger, "eth_getBalance", [poor.address, "latest"]), 16)
    price = balance // 30_000
    request = {"from": poor.address, "to": "0x" + "22" * 20, "gasPrice": hex(price)}
    assert result(pair.ledger, "eth_estimateGas", [request, "latest"]) == hex(21_000)
    request["gasPrice"] = hex(balance // 20_000)
    error = call(pair.ledger, "eth_estimateGas", [request, "latest"])["error"]
    assert error == {"code": -32000, "message": "gas required exceeds allowance (20000)"}
    request["value"] = hex(balance + 1)
    error = call(pair.ledger, "eth_estimateGas", [request, "latest"])["error"]
    assert error["message"].startswith("insufficient funds for gas * price + value: address ")
