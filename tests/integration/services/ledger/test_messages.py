"""Node messages clients classify by: an empty revert, too little gas, by-name parameters.

Each request goes to the ledger and to anvil; the answers are compared.
"""

from __future__ import annotations

from typing import Any

import httpx

from tests.integration.services.ledger.conftest import Pair, call, deploying, head
from tests.rawtx import RawTx

EMPTY_REVERT = bytes.fromhex("5f5ffd")  # PUSH0 PUSH0 REVERT


def test_an_empty_revert_is_plain_execution_reverted(pair: Pair) -> None:
    owner = pair.funded()
    ours, theirs = pair.deploy(owner, deploying(EMPTY_REVERT))
    for method in ("eth_call", "eth_estimateGas"):
        mine = call(pair.ledger, method, [{"to": ours}, "latest"])["error"]
        node = call(pair.anvil, method, [{"to": theirs}, "latest"])["error"]
        assert mine == {"code": 3, "message": "execution reverted", "data": "0x"}
        assert (node["code"], node["message"]) == (mine["code"], mine["message"])
        assert node.get("data", "0x") == mine["data"]


def test_too_little_gas_is_intrinsic_gas_too_low_on_both(pair: Pair) -> None:
    sender = pair.funded()
    raw = RawTx(gas=20_000, max_fee=10**11).sign(bytes(sender.account.key))
    mine = call(pair.ledger, "eth_sendRawTransaction", [raw])["error"]
    node = call(pair.anvil, "eth_sendRawTransaction", [raw])["error"]
    assert mine == {
        "code": -32000,
        "message": "intrinsic gas too low: gas 20000, minimum needed 21000",
    }
    assert node["message"] == "intrinsic gas too low"


def by_name(url: str, method: str, params: Any, request_id: int | None = 1) -> httpx.Response:
    payload: dict[str, Any] = {"jsonrpc": "2.0", "method": method, "params": params}
    if request_id is not None:
        payload["id"] = request_id
    return httpx.post(url, json=payload, timeout=30)


def test_parameters_by_name_are_invalid_params_on_both(pair: Pair) -> None:
    before = head(pair.service_url)
    for method, params in [
        ("eth_blockNumber", {}),
        ("eth_getBalance", {"address": "0x" + "11" * 20, "block": "latest"}),
        ("eth_sendRawTransaction", {"data": RawTx().sign(b"\x01" * 32)}),
    ]:
        mine = by_name(pair.ledger, method, params).json()
        node = by_name(pair.anvil, method, params).json()
        assert mine == {
            "jsonrpc": "2.0",
            "id": 1,
            "error": {
                "code": -32602,
                "message": "invalid params: expected an array of positional parameters",
            },
        }
        assert node["error"]["code"] == -32602
    assert head(pair.service_url) == before


def test_by_name_parameters_in_a_notification_are_not_answered(pair: Pair) -> None:
    response = by_name(pair.ledger, "eth_blockNumber", {}, request_id=None)
    assert response.status_code == 204
