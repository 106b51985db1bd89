"""Block parameters and quantities parsed as geth and anvil parse them, side by side with anvil:
a 32-byte string is a block hash where a block may be named by hash, quantities are ``0x``
and hex digits within their type's bits, and a call's fields are checked before it runs."""

from __future__ import annotations

from typing import Any, cast

import pytest

from services.ledger.rpc import EmbeddedMethods
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


HASH = "0x" + "22" * 32
"""A block or transaction hash neither chain holds (answered null where one is looked up)."""
TAKEN: dict[str, tuple[str, list[Any]]] = {
    "web3_clientVersion": ("web3_clientVersion", []),
    "web3_sha3": ("web3_sha3", ["0x"]),
    "net_version": ("net_version", []),
    "net_listening": ("net_listening", []),
    "eth_chainId": ("eth_chainId", []),
    "eth_protocolVersion": ("eth_protocolVersion", []),
    "eth_syncing": ("eth_syncing", []),
    "eth_mining": ("eth_mining", []),
    "eth_accounts": ("eth_accounts", []),
    "eth_coinbase": ("eth_coinbase", []),
    "eth_blockNumber": ("eth_blockNumber", []),
    "eth_gasPrice": ("eth_gasPrice", []),
    "eth_maxPriorityFeePerGas": ("eth_maxPriorityFeePerGas", []),
    "eth_feeHistory": ("eth_feeHistory", ["0x1", "latest", [50]]),
    "eth_getBlockByNumber": ("eth_getBlockByNumber", ["latest", False]),
    "eth_getBlockByHash": ("eth_getBlockByHash", [HASH, False]),
    "eth_getBlockTransactionCountByNumber": ("eth_getBlockTransactionCountByNumber", ["0x0"]),
    "eth_getBlockTransactionCountByHash": ("eth_getBlockTransactionCountByHash", [HASH]),
    "eth_getBlockReceipts": ("eth_getBlockReceipts", ["latest"]),
    "eth_getTransactionByHash": ("eth_getTransactionByHash", [HASH]),
    "eth_getTransactionReceipt": ("eth_getTransactionReceipt", [HASH]),
    "eth_getTransactionByBlockNumberAndIndex": (
        "eth_getTransactionByBlockNumberAndIndex",
        ["0x0", "0x0"],
    ),
    "eth_getTransactionByBlockHashAndIndex": (
        "eth_getTransactionByBlockHashAndIndex",
        [HASH, "0x0"],
    ),
    "eth_getBalance": ("eth_getBalance", [ADDRESS, "latest"]),
    "eth_getTransactionCount": ("eth_getTransactionCount", [ADDRESS, "latest"]),
    "eth_getCode": ("eth_getCode", [ADDRESS, "latest"]),
    "eth_getStorageAt": ("eth_getStorageAt", [ADDRESS, "0x0", "latest"]),
    "eth_call": ("eth_call", [{"to": ADDRESS}, "latest", None, None]),
    "eth_call-at-a-number": ("eth_call", [{"to": ADDRESS}, "0x0", None, None]),
    "eth_estimateGas": ("eth_estimateGas", [{"to": ADDRESS}, "latest", None, None]),
    "eth_createAccessList": ("eth_createAccessList", [{"to": ADDRESS}, "latest", None]),
    "eth_getLogs": ("eth_getLogs", [{"fromBlock": "0x0", "toBlock": "0x0"}]),
    "eth_newFilter": ("eth_newFilter", [{"fromBlock": "latest"}]),
    "eth_newBlockFilter": ("eth_newBlockFilter", []),
    "eth_getFilterChanges": ("eth_getFilterChanges", ["<block filter>"]),
    "eth_getFilterLogs": ("eth_getFilterLogs", ["<log filter>"]),
    "eth_uninstallFilter": ("eth_uninstallFilter", ["<log filter>"]),
}
"""A request per method of the ledger's table with every positional parameter geth's
signature has (``internal/ethapi/api.go``, ``eth/filters/api.go``, ``node/api.go``), each
valid: eth_call and eth_estimateGas take a state override and block overrides after the
block, eth_createAccessList a state override. ``eth_call`` at the head is answered on the
event loop, at a number on a worker thread: both are checked. eth_sendRawTransaction is
checked apart (its one parameter spends ether)."""
NOT_ON_ANVIL = {"eth_mining"}
"""Gone from geth and from anvil 1.7.1 (-32601); the ledger still answers it."""
ANVIL_TAKES_FEWER = {"eth_createAccessList"}
"""anvil 1.7.1 takes no state override here (-32602 `invalid length 3`); geth does."""


def taken(url: str, case: str) -> tuple[str, list[Any]]:
    """``TAKEN[case]`` for the node at ``url``, a filter parameter replaced by a filter of
    that node's, installed now."""
    method, params = TAKEN[case]
    kinds = {"<block filter>": ("eth_newBlockFilter", []), "<log filter>": ("eth_newFilter", [{}])}
    installed = [result(url, *kinds[p]) if isinstance(p, str) and p in kinds else p for p in params]
    return method, installed


@pytest.mark.parametrize("case", sorted(TAKEN))
def test_every_parameter_geth_takes_is_still_taken(pair: Pair, case: str) -> None:
    """A method's whole signature is answered, its optional trailing parameters included
    (null where geth takes a pointer: web3.py sends a state override there)."""
    for url in pair.urls:
        if url == pair.anvil and case in NOT_ON_ANVIL | ANVIL_TAKES_FEWER:
            continue
        answer = call(url, *taken(url, case))
        assert "result" in answer, (url, answer)


def refusals(pair: Pair, case: str, extra: list[Any]) -> list[Any]:
    """The errors the ledger and anvil (where it has the method) answer ``TAKEN[case]``
    with ``extra`` parameters after it; None where one answered a result."""
    errors = []
    for url in pair.urls:
        if url == pair.anvil and case in NOT_ON_ANVIL:
            continue
        method, params = taken(url, case)
        errors.append(call(url, method, [*params, *extra]).get("error"))
    return errors


def assert_too_many(errors: list[Any], most: int) -> None:
    """The ledger's error is geth's for more than ``most`` parameters; anvil's, in its own
    words, has the same code."""
    assert errors[0] == {"code": -32602, "message": f"too many arguments, want at most {most}"}
    codes = [error.get("code") if isinstance(error, dict) else error for error in errors]
    assert codes == [-32602] * len(errors), errors


@pytest.mark.parametrize("extra", [["x"], [None]], ids=["string", "null"])
@pytest.mark.parametrize("case", sorted(TAKEN))
def test_a_parameter_more_than_a_method_takes_is_invalid_params(
    pair: Pair, case: str, extra: list[Any]
) -> None:
    """The ledger ran the method and dropped what it did not read (``eth_chainId`` with
    ``[1, 2, 3]`` answered the chain id); geth refuses it with -32602 ``too many arguments,
    want at most N``, a null counted as any other value, and anvil with -32602 in its words."""
    assert_too_many(refusals(pair, case, extra), most=len(TAKEN[case][1]))


def test_the_reviewers_cases_are_refused_as_on_anvil(pair: Pair) -> None:
    """The two requests the review found answered."""
    cases = {
        ("eth_chainId", 0): [1, 2, 3],
        ("eth_getBalance", 2): [ADDRESS, "latest", "x"],
    }
    for (method, most), params in cases.items():
        assert_too_many([call(url, method, params).get("error") for url in pair.urls], most)


def test_a_raw_transaction_with_a_parameter_more_is_refused_not_sent(pair: Pair) -> None:
    """The transaction is refused whole, as geth and anvil refuse it, before it is read: the
    ledger used to send it (here: one its sender cannot pay for, -32000 before)."""
    raw = RawTx(to=bytes.fromhex(ADDRESS[2:]), value=1, max_fee=10**11).sign(bytes(range(1, 33)))
    answers = [call(url, "eth_sendRawTransaction", [raw, "x"]) for url in pair.urls]
    assert_too_many([answer.get("error") for answer in answers], most=1)


def test_every_method_the_ledger_serves_is_checked_here() -> None:
    """A method added to the ledger's table without a case above would go unchecked."""
    served = EmbeddedMethods(cast(Any, None), cast(Any, None), cast(Any, None)).table()
    checked = {method for method, _ in TAKEN.values()} | {"eth_sendRawTransaction"}
    assert checked == set(served)


@pytest.mark.parametrize(
    ("method", "params"),
    [
        ("eth_call", [{"to": IDENTITY, "data": "0x01"}, "latest", {ADDRESS: {"balance": "0x1"}}]),
        ("eth_call", [{"to": IDENTITY, "data": "0x01"}, "0x0", None, {"number": "0x10"}]),
        ("eth_estimateGas", [{"to": IDENTITY}, "latest", {ADDRESS: {"code": "0x00"}}]),
        ("eth_createAccessList", [{"to": IDENTITY}, "latest", {ADDRESS: {"nonce": "0x1"}}]),
    ],
    ids=["call-state", "call-block", "estimate-state", "access-list-state"],
)
def test_an_override_that_asks_for_something_is_refused_not_ignored(
    pair: Pair, method: str, params: list[Any]
) -> None:
    """The embedded chain cannot apply geth's state or block overrides; one taken and left
    unapplied answered another call than the one asked. Empty ones ask for nothing."""
    error = call(pair.ledger, method, params)["error"]
    assert error == {
        "code": -32602,
        "message": "state and block overrides are not supported by this node",
    }
    empty = [params[0], params[1], *({} for _ in params[2:])]
    assert "result" in call(pair.ledger, method, empty)
