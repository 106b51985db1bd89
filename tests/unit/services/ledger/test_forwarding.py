"""External-node mode's relay, against a real HTTP server playing the node: what reaches the
node, how its answers are matched back, and what a slow, busy, broken or absent node gives."""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import anyio

from services.common.slots import Slots
from services.ledger.endpoint import RpcEndpoint
from services.ledger.forwarding import NodeForwarder
from services.ledger.rpc import COSTLY_METHODS, Dispatcher
from tests.procs import free_port
from tests.scripted_http import Exchange, Reply, json_reply, scripted_server

CALL = {"to": "0x" + "11" * 20}


def endpoint(url: str, **options: Any) -> tuple[RpcEndpoint, NodeForwarder]:
    forwarder = NodeForwarder(
        url,
        options.pop("max_connections", 4),
        options.pop("call_timeout_s", 5.0),
        options.pop("connection_wait_s", 5.0),
    )
    dispatcher = Dispatcher({}, costly=COSTLY_METHODS)
    return RpcEndpoint(
        dispatcher, Slots("call", 1, options.pop("slot_wait_s", 5.0)), forwarder
    ), forwarder


def answer(
    url: str, *documents: Any, first_at_node: threading.Event | None = None, **options: Any
) -> list[Any]:
    """The endpoint's answers to ``documents``, all sent at once; when ``first_at_node`` is
    given, the others are sent only once it is set (the node has the first), so which one
    holds a slot does not depend on how busy the machine is."""
    rpc, forwarder = endpoint(url, **options)
    answers: list[Any] = [None] * len(documents)

    async def one(index: int, document: Any) -> None:
        answers[index] = await rpc.answer(json.dumps(document).encode())

    async def scenario() -> None:
        try:
            async with anyio.create_task_group() as tasks:
                for index, document in enumerate(documents):
                    tasks.start_soon(one, index, document)
                    if index == 0 and first_at_node is not None:
                        await anyio.to_thread.run_sync(first_at_node.wait, 10)
                    await anyio.sleep(0.05)
        finally:
            await forwarder.aclose()

    anyio.run(scenario)
    return answers


def request(method: str, params: Any, request_id: Any = 1) -> dict[str, Any]:
    sent = {"jsonrpc": "2.0", "method": method, "params": params}
    return sent if request_id is None else {**sent, "id": request_id}


def echo_node(exchange: Exchange) -> Reply:
    """Answers every request with its method and params, a batch in reverse order."""
    sent = json.loads(exchange.body)
    requests = sent if isinstance(sent, list) else [sent]
    answers = [
        {"jsonrpc": "2.0", "id": r["id"], "result": [r["method"], r["params"]]} for r in requests
    ]
    return json_reply(json.dumps(answers[::-1] if isinstance(sent, list) else answers[0]))


def test_a_batch_reaches_the_node_as_one_batch_of_its_standard_calls() -> None:
    batch = [
        request("eth_getBalance", ["0xab", "latest"], "a"),
        request("eth_chainId", [], None),
        request("anvil_mine", [], 2),
        {"jsonrpc": "1.0", "id": 3, "method": "eth_chainId"},
        request("eth_blockNumber", {"named": True}, 4),
        request("net_version", [], 5),
    ]
    with scripted_server(echo_node) as node:
        (answered,) = answer(node.url, batch)
        sent = [json.loads(exchange.body) for exchange in node.exchanges]
    assert [[r["method"] for r in exchange] for exchange in sent] == [
        ["eth_getBalance", "eth_chainId", "net_version"]
    ]
    assert answered == [
        {"jsonrpc": "2.0", "id": "a", "result": ["eth_getBalance", ["0xab", "latest"]]},
        {
            "jsonrpc": "2.0",
            "id": 2,
            "error": {
                "code": -32601,
                "message": "the method anvil_mine does not exist/is not available",
            },
        },
        {
            "jsonrpc": "2.0",
            "id": None,
            "error": {"code": -32600, "message": "not a JSON-RPC 2.0 request"},
        },
        {
            "jsonrpc": "2.0",
            "id": 4,
            "error": {
                "code": -32602,
                "message": "invalid params: expected an array of positional parameters",
            },
        },
        {"jsonrpc": "2.0", "id": 5, "result": ["net_version", []]},
    ]


def test_a_single_call_goes_alone_and_the_nodes_errors_come_back_unchanged() -> None:
    revert = {"code": 3, "message": "execution reverted: no", "data": "0x08c379a0"}

    def node_script(exchange: Exchange) -> Reply:
        sent = json.loads(exchange.body)
        return json_reply(json.dumps({"jsonrpc": "2.0", "id": sent["id"], "error": revert}))

    with scripted_server(node_script) as node:
        (answered,) = answer(node.url, request("eth_call", [CALL, "latest"], "x"))
        assert isinstance(json.loads(node.exchanges[0].body), dict)
    assert answered == {"jsonrpc": "2.0", "id": "x", "error": revert}


def test_nothing_to_relay_never_reaches_the_node() -> None:
    with scripted_server(echo_node) as node:
        answers = answer(node.url, request("debug_traceCall", [], 1), [request("x", [], None)])
        assert node.exchanges == []
    assert answers[0]["error"]["code"] == -32601
    assert answers[1] is None


def test_a_node_that_takes_longer_than_the_evm_timeout_times_the_call_out() -> None:
    def stalling(exchange: Exchange) -> Reply:
        time.sleep(3)
        return echo_node(exchange)

    with scripted_server(stalling) as node:
        started = time.monotonic()
        (answered,) = answer(node.url, request("eth_call", [CALL, "latest"]), call_timeout_s=0.5)
        waited = time.monotonic() - started
    assert answered == {
        "jsonrpc": "2.0",
        "id": 1,
        "error": {"code": -32002, "message": "request timed out"},
    }
    assert waited < 2.5


def test_when_every_connection_stays_busy_a_request_is_refused() -> None:
    first_at_node = threading.Event()

    def held(exchange: Exchange) -> Reply:
        first_at_node.set()
        time.sleep(1.0)
        return echo_node(exchange)

    with scripted_server(held) as node:
        first, second = answer(
            node.url,
            request("eth_blockNumber", [], 1),
            request("eth_chainId", [], 2),
            first_at_node=first_at_node,
            max_connections=1,
            connection_wait_s=0.3,
        )
    assert first == {"jsonrpc": "2.0", "id": 1, "result": ["eth_blockNumber", []]}
    assert second["error"] == {
        "code": -32005,
        "message": "limit exceeded: all 1 connections to the node stayed busy for 0.3 s; "
        "retry later",
    }


def test_a_costly_call_waits_for_a_call_slot_and_others_do_not() -> None:
    call_at_node = threading.Event()

    def node_script(exchange: Exchange) -> Reply:
        sent = json.loads(exchange.body)
        if isinstance(sent, dict) and sent["method"] == "eth_call":
            call_at_node.set()
            time.sleep(1.0)
        return echo_node(exchange)

    with scripted_server(node_script) as node:
        held, refused, read = answer(
            node.url,
            request("eth_call", [CALL, "latest"], 1),
            [request("eth_chainId", [], 2), request("eth_estimateGas", [CALL], 3)],
            request("eth_blockNumber", [], 4),
            first_at_node=call_at_node,
            slot_wait_s=0.3,
        )
    assert held["result"] == ["eth_call", [CALL, "latest"]]
    assert refused == {
        "jsonrpc": "2.0",
        "id": None,
        "error": {
            "code": -32005,
            "message": "limit exceeded: all 1 call slots stayed busy for 0.3 s; retry later",
        },
    }
    assert read["result"] == ["eth_blockNumber", []]


def test_what_is_not_an_answer_is_an_internal_error_for_each_call() -> None:
    replies = iter(
        [
            json_reply("<html>bad gateway</html>", status=502),
            json_reply(json.dumps([{"jsonrpc": "2.0", "id": 0, "result": "0x1"}])),
            json_reply(
                json.dumps(
                    {
                        "jsonrpc": "2.0",
                        "id": None,
                        "error": {"code": -32600, "message": "batch too large"},
                    }
                )
            ),
        ]
    )
    batch = [request("eth_chainId", [], 1), request("eth_blockNumber", [], 2)]
    with scripted_server(lambda _: next(replies)) as node:
        gateway, partial, refused = answer(node.url, batch, batch, batch)
    no_answer = {"code": -32603, "message": "the Ethereum node gave no answer"}
    assert [a["error"] for a in gateway] == [no_answer, no_answer]
    assert partial == [
        {"jsonrpc": "2.0", "id": 1, "result": "0x1"},
        {"jsonrpc": "2.0", "id": 2, "error": no_answer},
    ]
    too_large = {"code": -32600, "message": "batch too large"}
    assert [a["error"] for a in refused] == [too_large, too_large]


def test_an_unreachable_node_is_an_internal_error() -> None:
    (answered,) = answer(f"http://127.0.0.1:{free_port()}", request("eth_chainId", []))
    assert answered["error"] == {"code": -32603, "message": "the Ethereum node did not answer"}
