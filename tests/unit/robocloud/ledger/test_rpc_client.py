"""``JsonRpcClient`` against a scripted node on a real socket: errors, bounds and retries.

The retry rules are the point: a read is resent after a lost answer, a node-signed
``eth_sendTransaction`` never is (each copy would be a new transaction), and a resent
``eth_sendRawTransaction`` whose first copy did arrive is recognised by its hash.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import pytest
from eth_utils.crypto import keccak

from robocloud.errors import ApiError, InvalidAnswerError, PayloadTooLargeError, TransportError
from robocloud.ledger import JsonRpcClient, RpcError
from tests.scripted_http import Exchange, Reply, Script, json_reply, nested_json, scripted_server

RAW_TX = "0x" + bytes(range(40)).hex()
TX_HASH = "0x" + keccak(hexstr=RAW_TX).hex()


def node(answer: Callable[[str, list[Any]], Any]) -> Script:
    """A JSON-RPC node: ``answer(method, params)`` is the result, an error dict, or a Reply."""

    def script(exchange: Exchange) -> Reply:
        call = json.loads(exchange.body)
        outcome = answer(call["method"], call["params"])
        if outcome is None or isinstance(outcome, tuple):
            return outcome
        if isinstance(outcome, dict) and "error" in outcome:
            return json_reply(json.dumps({"jsonrpc": "2.0", "id": call["id"], **outcome}))
        return json_reply(json.dumps({"jsonrpc": "2.0", "id": call["id"], "result": outcome}))

    return script


def methods(exchanges: list[Exchange]) -> list[str]:
    return [json.loads(exchange.body)["method"] for exchange in exchanges]


def test_an_error_object_is_an_rpc_error_with_its_fields() -> None:
    error = {"error": {"code": 3, "message": "execution reverted", "data": "0x08c379a0"}}
    with (
        scripted_server(node(lambda *_: error)) as server,
        JsonRpcClient(server.url, retries=0) as rpc,
        pytest.raises(RpcError) as err,
    ):
        rpc.request("eth_call", [{}, "latest"])
    assert (err.value.method, err.value.code, err.value.data) == ("eth_call", 3, "0x08c379a0")
    assert err.value.status == 200


def test_the_services_error_model_is_an_api_error() -> None:
    body = b'{"error":{"code":"body_too_large","message":"limit","request_id":"r9"}}'
    with (
        scripted_server(lambda _: json_reply(body, 413)) as server,
        JsonRpcClient(server.url, retries=0) as rpc,
        pytest.raises(PayloadTooLargeError) as err,
    ):
        rpc.request("eth_blockNumber", [])
    assert (err.value.code, err.value.request_id) == ("body_too_large", "r9")


@pytest.mark.parametrize(
    "reply",
    [
        json_reply(nested_json(100_000)),
        json_reply(b'{"jsonrpc":"2.0","id":1}'),
        json_reply(b'{"jsonrpc":"2.0","id":999,"result":"0x1"}'),
        json_reply(b"[1, 2]"),
        json_reply(b"<html>"),
    ],
    ids=["nested", "no-result", "wrong-id", "not-an-object", "not-json"],
)
def test_an_answer_that_is_not_json_rpc_is_an_invalid_answer(reply: Reply) -> None:
    with (
        scripted_server(lambda _: reply) as server,
        JsonRpcClient(server.url, service="ledger", retries=0) as rpc,
        pytest.raises(InvalidAnswerError, match="the ledger service at"),
    ):
        rpc.request("eth_blockNumber", [])


def test_a_non_json_error_status_is_an_api_error() -> None:
    with (
        scripted_server(lambda _: (502, {"Content-Type": "text/html"}, b"<html>")) as server,
        JsonRpcClient(server.url, retries=0) as rpc,
        pytest.raises(ApiError) as err,
    ):
        rpc.request("eth_sendTransaction", [{}])
    assert err.value.status == 502


def losing_first_answers(count: int, answer: Callable[[str, list[Any]], Any]) -> Script:
    """A node that does the work of the first ``count`` requests but loses their answers."""
    seen = [0]

    def lossy(method: str, params: list[Any]) -> Any:
        seen[0] += 1
        result = answer(method, params)
        return None if seen[0] <= count else result

    return node(lossy)


def test_a_read_is_resent_after_a_lost_answer() -> None:
    with (
        scripted_server(losing_first_answers(2, lambda *_: "0x10")) as server,
        JsonRpcClient(server.url, retries=3, backoff_s=0.001) as rpc,
    ):
        assert rpc.request("eth_blockNumber", []) == "0x10"
    assert methods(server.exchanges) == ["eth_blockNumber"] * 3


def test_a_node_signed_transaction_is_never_resent() -> None:
    """``eth_sendTransaction`` signs each copy with a fresh nonce: a resend could pay twice."""
    with (
        scripted_server(losing_first_answers(1, lambda *_: TX_HASH)) as server,
        JsonRpcClient(server.url, retries=3, backoff_s=0.001) as rpc,
        pytest.raises(TransportError),
    ):
        rpc.request("eth_sendTransaction", [{"to": "0x00"}])
    assert methods(server.exchanges) == ["eth_sendTransaction"]


def test_a_resent_raw_transaction_the_node_already_has_answers_its_hash() -> None:
    """The first copy arrived but its answer was lost; the resend says "already known"."""
    pool: set[str] = set()

    def answer(method: str, params: list[Any]) -> Any:
        if method == "eth_getTransactionByHash":
            return {"hash": params[0]} if params[0] in pool else None
        tx_hash = "0x" + keccak(hexstr=params[0]).hex()
        if tx_hash in pool:
            return {"error": {"code": -32000, "message": "already known"}}
        pool.add(tx_hash)
        return tx_hash

    with (
        scripted_server(losing_first_answers(1, answer)) as server,
        JsonRpcClient(server.url, retries=3, backoff_s=0.001) as rpc,
    ):
        assert rpc.request("eth_sendRawTransaction", [RAW_TX]) == TX_HASH
    assert methods(server.exchanges) == [
        "eth_sendRawTransaction",
        "eth_sendRawTransaction",
        "eth_getTransactionByHash",
    ]
    assert pool == {TX_HASH}


def test_a_refused_raw_transaction_the_node_does_not_have_stays_an_error() -> None:
    def answer(method: str, params: list[Any]) -> Any:
        if method == "eth_getTransactionByHash":
            return None
        return {"error": {"code": -32000, "message": "nonce too low"}}

    with (
        scripted_server(losing_first_answers(1, answer)) as server,
        JsonRpcClient(server.url, retries=3, backoff_s=0.001) as rpc,
        pytest.raises(RpcError, match="nonce too low"),
    ):
        rpc.request("eth_sendRawTransaction", [RAW_TX])
    assert methods(server.exchanges)[-1] == "eth_getTransactionByHash"


def test_a_first_time_refusal_of_a_raw_transaction_is_not_looked_up() -> None:
    """Without a resend nothing can have arrived before: the node's error is the answer."""
    refusal = {"error": {"code": -32000, "message": "already known"}}
    with (
        scripted_server(node(lambda *_: refusal)) as server,
        JsonRpcClient(server.url, retries=3) as rpc,
        pytest.raises(RpcError),
    ):
        rpc.request("eth_sendRawTransaction", [RAW_TX])
    assert methods(server.exchanges) == ["eth_sendRawTransaction"]
