"""Invalid transactions refused before anything is mined, side by side with anvil.

Each transaction is built byte for byte (``rawtx``) and sent to the ledger and to a fresh
anvil from a funded account on each. Where anvil's message is geth's, the ledger's message
starts with it (geth adds the figures); where anvil accepts what geth refuses (the calldata
floor, oversized transactions, unprotected signatures) the ledger follows geth.
"""

from __future__ import annotations

from typing import Any

import pytest

from robocloud.identity import Identity
from tests.integration.services.ledger.conftest import Pair, Service, call, faucet, head
from tests.rawtx import RawTx

BASE = RawTx(max_fee=10**11, max_priority_fee=10**9, gas_price=10**11)


def send_both(pair: Pair, build: Any, **forge: Any) -> tuple[dict[str, Any], dict[str, Any], str]:
    """Send ``build(identity)`` signed by a fresh funded key to both; both error objects."""
    identity = pair.funded()
    raw = build(identity).sign(bytes(identity.account.key), **forge)
    before = head(pair.ledger.removesuffix("/rpc"))
    ours = call(pair.ledger, "eth_sendRawTransaction", [raw])
    theirs = call(pair.anvil, "eth_sendRawTransaction", [raw])
    assert "error" in ours, ours
    assert "error" in theirs, theirs
    assert head(pair.ledger.removesuffix("/rpc")) == before
    count = call(pair.ledger, "eth_getTransactionCount", [identity.address, "latest"])
    assert count["result"] == "0x0"
    return ours["error"], theirs["error"], identity.address


SAME_AS_ANVIL = {
    "tip-above-cap": (
        lambda i: BASE.but(max_fee=10**10, max_priority_fee=10**10 + 1),
        "max priority fee per gas higher than max fee per gas",
    ),
    "intrinsic-gas-dynamic": (lambda i: BASE.but(gas=20_999), "intrinsic gas too low"),
    "intrinsic-gas-legacy": (lambda i: BASE.but(kind=0, gas=20_999), "intrinsic gas too low"),
    "fee-cap-below-base-fee": (
        lambda i: BASE.but(max_fee=1, max_priority_fee=0),
        "max fee per gas less than block base fee",
    ),
    "legacy-price-below-base-fee": (
        lambda i: BASE.but(kind=0, gas_price=1),
        "max fee per gas less than block base fee",
    ),
    "initcode-too-large": (
        lambda i: BASE.but(to=b"", data=b"\x00" * 49_153, gas=10_000_000),
        "max initcode size exceeded",
    ),
    "insufficient-funds": (
        lambda i: BASE.but(value=10**21),
        "insufficient funds for gas * price + value",
    ),
}


@pytest.mark.parametrize("case", sorted(SAME_AS_ANVIL))
def test_refused_with_the_nodes_message(pair: Pair, case: str) -> None:
    build, message = SAME_AS_ANVIL[case]
    ours, theirs, _ = send_both(pair, build)
    assert ours["code"] == -32000
    assert ours["message"].startswith(message), ours
    assert theirs["message"].lower().startswith(message), theirs


def test_the_messages_carry_geths_figures(pair: Pair) -> None:
    ours, _, sender = send_both(pair, lambda i: BASE.but(gas=20_999))
    assert ours["message"] == "intrinsic gas too low: gas 20999, minimum needed 21000"
    ours, _, sender = send_both(pair, lambda i: BASE.but(max_fee=1, max_priority_fee=0))
    assert ours["message"].startswith(
        f"max fee per gas less than block base fee: address {sender.lower()}, maxFeePerGas: 1, "
        "baseFee: "
    )
    ours, _, _ = send_both(pair, lambda i: BASE.but(to=b"", data=b"\x00" * 49_153, gas=10**7))
    assert ours["message"] == "max initcode size exceeded: code size 49153, limit 49152"


REFUSED_BY_BOTH = {
    "gas-above-block-limit": (lambda i: BASE.but(gas=10**9), -32000, "exceeds block gas limit"),
    "fee-cap-above-uint256": (
        lambda i: BASE.but(max_fee=2**256, max_priority_fee=1),
        -32000,
        "max fee per gas higher than 2^256-1",
    ),
    "tip-above-uint256": (
        lambda i: BASE.but(max_fee=2**256, max_priority_fee=2**256),
        -32000,
        "max fee per gas higher than 2^256-1",
    ),
    "value-above-uint256": (
        lambda i: BASE.but(value=2**256),
        -32602,
        "invalid raw transaction: value higher than 2^256-1",
    ),
    "access-list-short-address": (
        lambda i: BASE.but(access_list=[[b"\x01" * 19, []]]),
        -32602,
        "invalid raw transaction",
    ),
    "other-chain-access-list": (
        lambda i: BASE.but(kind=1, chain_id=5),
        -32000,
        "invalid chain id 5: this chain's id is 1337",
    ),
    "other-chain-dynamic": (
        lambda i: BASE.but(chain_id=1),
        -32000,
        "invalid chain id 1: this chain's id is 1337",
    ),
}


@pytest.mark.parametrize("case", sorted(REFUSED_BY_BOTH))
def test_refused_by_both(pair: Pair, case: str) -> None:
    build, code, message = REFUSED_BY_BOTH[case]
    ours, _, _ = send_both(pair, build)
    assert ours["code"] == code
    assert ours["message"].startswith(message), ours


@pytest.mark.parametrize(
    "forge",
    [{"v": 2}, {"r": 0}, {"s": 0}, {"s": 2**256 - 1}],
    ids=["parity-2", "r-0", "s-0", "s-max"],
)
def test_forged_signatures_are_invalid_params_on_both(pair: Pair, forge: dict[str, int]) -> None:
    ours, theirs, _ = send_both(pair, lambda i: BASE, **forge)
    assert ours["code"] == theirs["code"] == -32602
    assert ours["message"].startswith("invalid raw transaction")


def send_ledger(service: Service, tx: RawTx, **forge: Any) -> dict[str, Any]:
    identity = Identity.generate()
    assert faucet(service.url, identity).status_code == 200
    before = head(service.url)
    answer = call(
        f"{service.url}/rpc",
        "eth_sendRawTransaction",
        [tx.sign(bytes(identity.account.key), **forge)],
    )
    assert head(service.url) == before
    count = call(f"{service.url}/rpc", "eth_getTransactionCount", [identity.address, "latest"])
    assert count["result"] == "0x0"
    error: dict[str, Any] = answer["error"]
    return error


def test_calldata_below_the_eip_7623_floor_is_refused_as_geth_does(service: Service) -> None:
    error = send_ledger(service, BASE.but(data=b"\x01" * 1000, gas=21_000 + 16 * 1000))
    assert error == {
        "code": -32000,
        "message": "insufficient gas for floor data gas cost: gas 37000, minimum needed 61000",
    }


def test_access_lists_count_in_the_intrinsic_gas_as_geth_counts_them(service: Service) -> None:
    """anvil 1.7.1 admits this one and fails it in the block; geth refuses it."""
    tx = BASE.but(kind=1, gas=21_000, access_list=[[b"\x22" * 20, [b"\x00" * 32]]])
    error = send_ledger(service, tx)
    assert error["message"] == "intrinsic gas too low: gas 21000, minimum needed 25300"


def test_oversized_transaction_is_refused_as_geth_does(service: Service) -> None:
    error = send_ledger(service, BASE.but(data=b"\x01" * 140_000, gas=30_000_000))
    assert error["code"] == -32000
    assert error["message"].startswith("oversized data: transaction size ")
    assert error["message"].endswith(", limit 131072")


def test_nonce_at_the_eip_2681_bound_is_refused(service: Service) -> None:
    error = send_ledger(service, BASE.but(nonce=2**64 - 1))
    assert error["message"].startswith("nonce has max value: address 0x")
    error = send_ledger(service, BASE.but(nonce=2**64))
    assert error == {"code": -32602, "message": "invalid raw transaction: nonce higher than 2^64-1"}


def test_signatures_without_replay_protection_or_with_high_s_are_refused(
    service: Service,
) -> None:
    error = send_ledger(service, BASE.but(kind=0), v=27)
    assert error["message"].startswith("only replay-protected (EIP-155) transactions")
    error = send_ledger(service, BASE, s_high=True)
    assert error["code"] == -32000
    assert "S value" in error["message"]


def test_a_valid_transaction_from_the_same_builder_is_mined(service: Service) -> None:
    """The refusals above are the fields' fault, not the builder's."""
    identity = Identity.generate()
    assert faucet(service.url, identity).status_code == 200
    for kind in (0, 1, 2):
        raw = BASE.but(kind=kind, nonce=kind).sign(bytes(identity.account.key))
        answer = call(f"{service.url}/rpc", "eth_sendRawTransaction", [raw])
        receipt = call(f"{service.url}/rpc", "eth_getTransactionReceipt", [answer["result"]])
        assert receipt["result"]["status"] == "0x1"
        assert receipt["result"]["type"] == hex(kind)


# Creation code that stops only when it is given more gas than EIP-7825 lets a transaction
# carry (GAS, PUSH4 2^24, GT, JUMPI to INVALID, else STOP).
NEEDS_MORE_THAN_THE_CAP = bytes.fromhex("5a630100000011600b57005bfe")


def test_gas_above_the_eip_7825_cap_is_refused_as_geth_does(service: Service) -> None:
    """One transaction at the block gas limit (30 M) running a loop held the chain's lock
    for 6.4-9.5 s; the cap (geth's since Osaka) bounds that stall to about half."""
    price = int(call(f"{service.url}/rpc", "eth_gasPrice", [])["result"], 16)
    error = send_ledger(service, BASE.but(gas=2**24 + 1, max_fee=price))
    assert error == {
        "code": -32000,
        "message": "transaction gas limit too high (cap: 16777216, tx: 16777217)",
    }
    identity = Identity.generate()
    assert faucet(service.url, identity).status_code == 200
    raw = BASE.but(gas=2**24, max_fee=price).sign(bytes(identity.account.key))
    answer = call(f"{service.url}/rpc", "eth_sendRawTransaction", [raw])
    receipt = call(f"{service.url}/rpc", "eth_getTransactionReceipt", [answer["result"]])
    assert receipt["result"]["status"] == "0x1"
    request = {"data": "0x" + NEEDS_MORE_THAN_THE_CAP.hex()}
    estimate = call(f"{service.url}/rpc", "eth_estimateGas", [request])
    assert estimate["error"] == {
        "code": -32000,
        "message": "gas required exceeds allowance (16777216)",
    }
