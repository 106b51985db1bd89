"""Block parameters and quantities parsed as geth and anvil parse them, side by side with anvil:
a 32-byte string is a block hash where a block may be named by hash, quantities are ``0x``
and hex digits within their type's bits, and a call's fields are checked before it runs."""

from __future__ import annotations

from typing import Any

import pytest

from tests.integration.services.ledger.conftest import Pair, call, mined, result
from tests.rawtx import RawTx

ONE = "0x" + "00" * 31 + "01"
"""A 32-byte string that a block-number parser would read as block 1."""


def test_a_block_hash_string_names_its_block_as_on_anvil(pair: Pair) -> None:
    """A hash as a plain string was read as a (huge) block number, and ``0x00..01`` as
    block 1; geth and anvil read a 32-byte string as a hash (EIP-1898)."""
    sender = pair.funded()
    recipient = "0x" + "5e" * 20
    answers = []
    for url in pair.urls:
        tx = RawTx(to=bytes.fromhex(recipient[2:]), value=7, max_fee=10**11)
        tx_hash = result(url, "eth_sendRawTransaction", [tx.sign(bytes(sender.account.key))])
        receipt = mined(url, tx_hash)
        block_hash, number = receipt["blockHash"], receipt["blockNumber"]
        result(url, "eth_sendRawTransaction", [tx.but(nonce=1).sign(bytes(sender.account.key))])
        seen = {}
        for name, params in {
            "eth_getBalance": [recipient],
            "eth_getTransactionCount": [sender.address],
            "eth_getCode": [recipient],
            "eth_getStorageAt": [recipient, "0x0"],
            "eth_call": [{"to": recipient}],
        }.items():
            by_hash = result(url, name, [*params, block_hash])
            assert by_hash == result(url, name, [*params, {"blockHash": block_hash}])
            assert by_hash == result(url, name, [*params, number])
            seen[name] = by_hash
        assert seen["eth_getBalance"] == "0x7"
        assert seen["eth_getTransactionCount"] == "0x1"
        assert result(url, "eth_getBlockReceipts", [block_hash]) == [receipt]
        assert result(url, "eth_getBlockReceipts", [ONE]) is None
        assert result(url, "eth_getBlockReceipts", [{"blockHash": ONE}]) is None
        assert "error" in call(url, "eth_getBalance", [recipient, ONE])
        assert call(url, "eth_getBlockByNumber", [block_hash, False])["error"]["code"] == -32602
        answers.append(seen)
    assert answers[0] == answers[1]


ADDRESS = "0x" + "11" * 20
INVALID_ON_BOTH = {
    "slot-past-256-bits": ("eth_getStorageAt", [ADDRESS, "0x1" + "00" * 32, "latest"]),
    "underscore": ("eth_getBalance", [ADDRESS, "0x1_0"]),
    "trailing-space": ("eth_getBalance", [ADDRESS, "0x1 "]),
    "non-ascii-digit": ("eth_getBalance", [ADDRESS, "0x\uff11"]),
    "empty": ("eth_getBalance", [ADDRESS, "0x"]),
    "no-prefix": ("eth_getBalance", [ADDRESS, "10"]),
    "block-past-64-bits": ("eth_getBlockByNumber", [hex(2**64), False]),
    "index-underscore": ("eth_getTransactionByBlockNumberAndIndex", ["0x0", "0x1_0"]),
    "object-as-block-number": ("eth_getBlockByNumber", [{"blockNumber": "0x1"}, False]),
    "call-to-empty": ("eth_call", [{"to": "", "data": "0x"}, "latest"]),
    "call-from-empty": ("eth_call", [{"from": "", "to": ADDRESS}, "latest"]),
    "estimate-to-empty": ("eth_estimateGas", [{"to": "", "data": "0x"}]),
    "call-gas-past-64-bits": ("eth_call", [{"to": ADDRESS, "gas": hex(2**64)}, "latest"]),
    "estimate-gas-past-64-bits": ("eth_estimateGas", [{"to": ADDRESS, "gas": hex(2**64)}]),
    "call-value-past-256-bits": ("eth_call", [{"to": ADDRESS, "value": hex(2**256)}, "latest"]),
    "call-tip-above-cap": (
        "eth_call",
        [{"to": ADDRESS, "maxFeePerGas": "0x1", "maxPriorityFeePerGas": "0x2"}, "latest"],
    ),
    "full-flag-string": ("eth_getBlockByNumber", ["latest", "false"]),
    "full-flag-number": ("eth_getBlockByNumber", ["0x0", 0]),
    "full-flag-hex": ("eth_getBlockByNumber", ["latest", "0x1"]),
    "full-flag-by-hash": ("eth_getBlockByHash", [ONE, "true"]),
}


@pytest.mark.parametrize("case", sorted(INVALID_ON_BOTH))
def test_malformed_parameters_are_invalid_params_on_both(pair: Pair, case: str) -> None:
    """Slots past 2^256 were -32603 (an internal error); ``int(x, 16)`` took ``0x1_0``,
    whitespace and non-ASCII digits; a call's gas past 2^64 and a tip above its fee cap
    ran; a full-transactions flag that is not a boolean was read by its truth (``"false"``
    answered the block with its full transactions)."""
    method, params = INVALID_ON_BOTH[case]
    errors = [call(url, method, params).get("error") for url in pair.urls]
    assert errors[0] is not None, errors
    assert errors[1] is not None, errors
    assert errors[0]["code"] == errors[1]["code"] == -32602, errors
    if case == "call-tip-above-cap":
        assert errors[0] == errors[1]


ACCEPTED_ON_BOTH: dict[str, tuple[str, list[Any]]] = {
    "leading-zero-block": ("eth_getBlockByNumber", ["0x00", False]),
    "upper-case-prefix": ("eth_getBalance", [ADDRESS, "0X0"]),
    "short-slot": ("eth_getStorageAt", [ADDRESS, "0x1", "latest"]),
    "full-slot": ("eth_getStorageAt", [ADDRESS, "0x" + "00" * 31 + "01", "latest"]),
    "decimal-block-count": ("eth_feeHistory", ["1", "latest", []]),
    "call-gas-64-bits": ("eth_call", [{"to": ADDRESS, "gas": hex(2**64 - 1)}, "latest"]),
}


@pytest.mark.parametrize("case", sorted(ACCEPTED_ON_BOTH))
def test_what_anvil_accepts_is_accepted(pair: Pair, case: str) -> None:
    method, params = ACCEPTED_ON_BOTH[case]
    answers = [call(url, method, params) for url in pair.urls]
    assert "result" in answers[0], answers
    assert "result" in answers[1], answers
    if method == "eth_getBlockByNumber":
        assert answers[0]["result"]["number"] == answers[1]["result"]["number"] == "0x0"


def test_an_estimate_with_a_tip_above_its_fee_cap_is_refused_as_geth_does(pair: Pair) -> None:
    """geth refuses it (anvil 1.7.1 estimates it, though its eth_call refuses it)."""
    request = {"to": ADDRESS, "maxFeePerGas": "0x1", "maxPriorityFeePerGas": "0x2"}
    error = call(pair.ledger, "eth_estimateGas", [request])["error"]
    assert error == {
        "code": -32602,
        "message": "Invalid input: `max_priority_fee_per_gas` greater than `max_fee_per_gas`",
    }


IDENTITY = "0x" + "00" * 19 + "04"
"""The identity precompile: a call to it answers its own call data."""


def test_a_null_input_leaves_a_call_its_data_as_on_anvil(pair: Pair) -> None:
    """geth and anvil read a call's ``input``, or its ``data`` where ``input`` is absent or
    null; the ledger read ``input`` whenever the key was there, so ``{"input": null, "data":
    ...}`` ran with no data: ``eth_call`` answered ``0x`` and the estimate and access list
    were those of another call."""
    data = "0x" + "ab" * 40
    both = {"to": IDENTITY, "input": None, "data": data}
    for url in pair.urls:
        assert result(url, "eth_call", [both, "latest"]) == data
        assert result(url, "eth_call", [both, "0x0"]) == data
    plain = {"to": IDENTITY, "data": data}
    for method in ("eth_estimateGas", "eth_createAccessList"):
        assert result(pair.ledger, method, [both]) == result(pair.ledger, method, [plain])
    assert int(result(pair.ledger, "eth_estimateGas", [both]), 16) > 21_000 + 16 * 40
