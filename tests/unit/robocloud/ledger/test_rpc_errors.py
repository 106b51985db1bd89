"""Revert reasons are found in the error shapes that real nodes send back."""

from __future__ import annotations

import httpx
import pytest
from eth_abi.abi import encode

from robocloud.errors import ApiError
from robocloud.ledger.abi import ERROR_SELECTOR, ContractAbi
from robocloud.ledger.errors import RpcError
from robocloud.ledger.rpc import JsonRpcClient, as_revert

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


def test_a_nodes_megabyte_error_page_is_not_kept_whole_in_the_error() -> None:
    """A node answering HTTP 500 with a 30 MiB JSON error message raised an ApiError of that
    size, which the storage node kept as its last anchoring error, logged and served."""
    huge = "x" * (30 << 20)

    def answer(request: httpx.Request) -> httpx.Response:
        return httpx.Response(500, json={"error": {"code": "internal", "message": huge}})

    with (
        JsonRpcClient("http://node/rpc", transport=httpx.MockTransport(answer), retries=0) as rpc,
        pytest.raises(ApiError) as error,
    ):
        rpc.request("eth_chainId", [])
    assert len(str(error.value)) < 2_000
    assert str(error.value).endswith(f"... ({len(huge)} characters)")
    assert error.value.message == huge
