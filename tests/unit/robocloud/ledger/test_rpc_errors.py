"""Revert reasons are found in the error shapes that real nodes send back."""

from __future__ import annotations

from eth_abi.abi import encode

from robocloud.ledger.abi import ERROR_SELECTOR, ContractAbi
from robocloud.ledger.errors import RpcError
from robocloud.ledger.rpc import as_revert

REASON = "Registry: already registered"
DATA = "0x" + (ERROR_SELECTOR + encode(["string"], [REASON])).hex()
CONTRACTS = [ContractAbi.load("Registry")]


def test_geth_and_anvil_shape_code_3_with_hex_data() -> None:
    error = RpcError("eth_estimateGas", 3, f"execution reverted: {REASON}", DATA)
    revert = as_revert(error, CONTRACTS)
    assert revert is not None
    assert revert.reason == REASON
    assert revert.data.hex() == DATA[2:]
    assert revert.tx_hash is None


def test_hardhat_shape_nested_data() -> None:
    error = RpcError("eth_call", -32603, "Error: VM Exception: execution reverted", {"data": DATA})
    revert = as_revert(error, CONTRACTS)
    assert revert is not None
    assert revert.reason == REASON


def test_message_only_shape() -> None:
    revert = as_revert(RpcError("eth_call", -32000, f"execution reverted: {REASON}"), CONTRACTS)
    assert revert is not None
    assert revert.reason == REASON
    bare = as_revert(RpcError("eth_call", -32000, "execution reverted"), CONTRACTS)
    assert bare is not None
    assert bare.reason == "execution reverted without a reason"


def test_other_errors_are_not_reverts() -> None:
    assert as_revert(RpcError("eth_sendRawTransaction", -32000, "nonce too low"), CONTRACTS) is None
    assert as_revert(RpcError("eth_call", -32602, "invalid params", "0xzz"), CONTRACTS) is None
