"""The JSON-RPC 2.0 envelope, apart from any chain: batches, notifications, every error code."""

from __future__ import annotations

import json
import time
from typing import Any, cast

import pytest

from services.ledger.chain import ChainError, Reverted
from services.ledger.index import IndexLimitError
from services.ledger.rpc import (
    INTERNAL_ERROR,
    INVALID_PARAMS,
    INVALID_REQUEST,
    MAX_BATCH,
    METHOD_NOT_FOUND,
    NOT_INLINE,
    PARSE_ERROR,
    REQUEST_TIMED_OUT,
    RESPONSE_TOO_LARGE,
    Dispatcher,
    EmbeddedMethods,
    EncodedBatch,
    NotInline,
    RpcFailure,
    at_most,
)


def fail(exception: Exception) -> Any:
    def method(_: list[Any]) -> Any:
        raise exception

    return method


DISPATCHER = Dispatcher(
    {
        "echo": lambda params: params,
        "refuse": fail(RpcFailure(-32602, "bad argument", {"field": 0})),
        "chain": fail(ChainError("nonce too low")),
        "revert": fail(Reverted(bytes.fromhex("08c379a0") + bytes(96))),
        "index": fail(IndexLimitError("too many logs")),
        "crash": fail(KeyError("secret internals")),
    }
)


def call(method: str, params: Any = None, request_id: Any = 1) -> dict[str, Any]:
    request: dict[str, Any] = {"jsonrpc": "2.0", "method": method, "id": request_id}
    if params is not None:
        request["params"] = params
    return request


def body(document: Any) -> bytes:
    return json.dumps(document).encode()


def decoded(answer: Any) -> Any:
    """An answer as a client reads it (a batch's comes encoded)."""
    return json.loads(answer.body()) if isinstance(answer, EncodedBatch) else answer


def handle(document: Any) -> Any:
    return decoded(DISPATCHER.handle(body(document)))


def test_a_call_is_answered_with_its_id() -> None:
    assert handle(call("echo", [1, "a"], "x")) == {"jsonrpc": "2.0", "id": "x", "result": [1, "a"]}


def test_a_notification_gets_no_answer_even_when_it_fails() -> None:
    notification = {"jsonrpc": "2.0", "method": "echo", "params": []}
    assert handle(notification) is None
    assert handle({**notification, "method": "crash"}) is None


@pytest.mark.parametrize(
    ("method", "code", "message"),
    [
        ("missing", METHOD_NOT_FOUND, "the method missing does not exist/is not available"),
        ("refuse", -32602, "bad argument"),
        ("chain", -32000, "nonce too low"),
        ("index", -32005, "too many logs"),
        ("crash", INTERNAL_ERROR, "internal error in crash"),
    ],
)
def test_failures_become_error_objects(method: str, code: int, message: str) -> None:
    answer = handle(call(method, []))
    assert answer["id"] == 1
    assert (answer["error"]["code"], answer["error"]["message"]) == (code, message)
    assert "secret" not in json.dumps(answer)


def test_a_revert_carries_code_3_and_its_data() -> None:
    error = handle(call("revert", []))["error"]
    assert error["code"] == 3
    assert error["data"].startswith("0x08c379a0")


@pytest.mark.parametrize(
    "document",
    [
        {"method": "echo", "id": 1},
        {"jsonrpc": "1.0", "method": "echo", "id": 1},
        {"jsonrpc": "2.0", "method": 7, "id": 1},
        {"jsonrpc": "2.0", "method": "echo", "params": "positional", "id": 1},
        "just a string",
    ],
)
def test_malformed_requests_are_invalid(document: Any) -> None:
    assert handle(document)["error"]["code"] == INVALID_REQUEST


def test_parameters_by_name_are_invalid_params() -> None:
    """A well-formed request whose parameters Ethereum methods cannot take (as geth says)."""
    answer = handle({"jsonrpc": "2.0", "method": "echo", "params": {"named": 1}, "id": 1})
    assert answer["id"] == 1
    assert answer["error"] == {
        "code": -32602,
        "message": "invalid params: expected an array of positional parameters",
    }


def test_a_batch_answers_each_call_and_skips_notifications() -> None:
    answers = handle(
        [call("echo", [1], 1), {"jsonrpc": "2.0", "method": "echo"}, call("missing", [], 2)]
    )
    assert [answer["id"] for answer in answers] == [1, 2]
    assert answers[0]["result"] == [1]
    assert answers[1]["error"]["code"] == METHOD_NOT_FOUND


def test_a_batch_of_notifications_only_gets_no_answer() -> None:
    assert handle([{"jsonrpc": "2.0", "method": "echo"}] * 3) is None


def test_empty_and_oversized_batches_are_invalid() -> None:
    assert handle([])["error"]["code"] == INVALID_REQUEST
    assert handle([call("echo", [])] * (MAX_BATCH + 1))["error"]["code"] == INVALID_REQUEST


def test_bodies_that_are_not_json_are_parse_errors() -> None:
    assert DISPATCHER.handle(b'{"jsonrpc": ')["error"]["code"] == PARSE_ERROR
    assert DISPATCHER.handle(b"\xff")["error"]["code"] == PARSE_ERROR


def _needs_thread(_: list[Any]) -> Any:
    raise NotInline()


INLINE = Dispatcher(
    {"echo": lambda params: ["threaded", *params], "slow": lambda params: "threaded"},
    inline={"echo": lambda params: ["inline", *params], "slow": _needs_thread},
)


def test_inline_methods_answer_on_the_callers_thread() -> None:
    request = {"jsonrpc": "2.0", "id": 3, "method": "echo", "params": [1]}
    assert INLINE.answer_inline(request) == {"jsonrpc": "2.0", "id": 3, "result": ["inline", 1]}


@pytest.mark.parametrize(
    "document",
    [
        {"jsonrpc": "2.0", "id": 1, "method": "slow", "params": []},
        {"jsonrpc": "2.0", "id": 1, "method": "unknown", "params": []},
        [{"jsonrpc": "2.0", "id": 1, "method": "echo", "params": []}],
        "not a request",
    ],
    ids=["raises-not-inline", "not-an-inline-method", "batch", "malformed"],
)
def test_everything_else_goes_to_a_thread(document: Any) -> None:
    assert INLINE.answer_inline(document) is NOT_INLINE
    assert INLINE.answer(document) is not None


def test_costly_requests_are_those_naming_a_costly_method() -> None:
    dispatcher = Dispatcher({"cheap": lambda _: 1, "costly": lambda _: 2}, costly=["costly"])
    assert dispatcher.costly(call("costly", []))
    assert dispatcher.costly([call("cheap", []), call("costly", [], 2)])
    assert not dispatcher.costly(call("cheap", []))
    assert not dispatcher.costly([call("cheap", []), "junk", {"method": ["costly"]}])
    assert not dispatcher.costly("junk")


def test_a_batch_starts_no_call_after_its_deadline_as_geth_answers_them() -> None:
    started: list[int] = []

    def slow(params: list[Any]) -> Any:
        started.append(params[0])
        time.sleep(0.06)
        return params[0]

    dispatcher = Dispatcher({"slow": slow}, batch_timeout_s=0.1)
    answers = decoded(
        dispatcher.handle(
            body(
                [
                    *(call("slow", [n], n) for n in range(5)),
                    {"jsonrpc": "2.0", "method": "slow", "params": [99]},
                    {"jsonrpc": "1.0", "id": 7},
                ]
            )
        )
    )
    assert started == [0, 1]
    assert answers[:2] == [{"jsonrpc": "2.0", "id": n, "result": n} for n in range(2)]
    timed_out = {"code": REQUEST_TIMED_OUT, "message": "request timed out"}
    assert answers[2:5] == [{"jsonrpc": "2.0", "id": n, "error": timed_out} for n in range(2, 5)]
    assert answers[5]["error"]["code"] == INVALID_REQUEST  # framing is still checked
    assert len(answers) == 6  # and the notification left unstarted gets no answer either


def test_a_batch_runs_no_call_once_its_answers_pass_the_bound_as_geth_answers_them() -> None:
    """100 eth_getLogs of a large block, a 9 KB request, answered 142 MB."""
    started: list[int] = []

    def big(params: list[Any]) -> Any:
        started.append(params[0])
        return "x" * 400

    dispatcher = Dispatcher({"big": big}, batch_response_max_bytes=1000)
    batch = [
        *(call("big", [n], n) for n in range(5)),
        {"jsonrpc": "2.0", "method": "big", "params": [99]},
        {"jsonrpc": "1.0", "id": 7},
    ]
    answer = dispatcher.handle(body(batch))
    assert isinstance(answer, EncodedBatch)
    assert len(answer.body()) < 1000 + 2 * 500
    answers = json.loads(answer.body())
    assert started == [0, 1, 2]  # the one that passed the bound is answered whole
    assert [a["result"] for a in answers[:3]] == ["x" * 400] * 3
    too_large = {"code": RESPONSE_TOO_LARGE, "message": "response too large"}
    assert answers[3:5] == [{"jsonrpc": "2.0", "id": n, "error": too_large} for n in (3, 4)]
    assert answers[5]["error"]["code"] == INVALID_REQUEST
    assert len(answers) == 6


def test_a_refusal_answers_a_whole_request_as_its_framing_allows() -> None:
    failure = RpcFailure(-32005, "limit exceeded")
    error = {"code": -32005, "message": "limit exceeded"}
    assert DISPATCHER.refusal(call("echo", [], 9), failure) == {
        "jsonrpc": "2.0",
        "id": 9,
        "error": error,
    }
    assert DISPATCHER.refusal(call("echo", [], [1]), failure)["id"] is None  # not a valid id
    assert DISPATCHER.refusal({"jsonrpc": "2.0", "method": "echo"}, failure) is None
    assert DISPATCHER.refusal([call("echo", [], 1)], failure) == {
        "jsonrpc": "2.0",
        "id": None,
        "error": error,
    }


def test_a_method_refuses_more_parameters_than_it_takes_before_it_runs() -> None:
    """geth's words and code for one parameter too many; as many or fewer still run (the
    method decides which of its trailing ones are optional)."""
    ran: list[list[Any]] = []

    def record(params: list[Any]) -> int:
        ran.append(params)
        return len(params)

    dispatcher = Dispatcher({"two": at_most(2, record), "none": at_most(0, record)})
    assert DISPATCHER.answer(call("echo", [1, 2, 3]))["result"] == [1, 2, 3]  # unbounded
    assert [dispatcher.answer(call("two", p))["result"] for p in ([], [1], [1, None])] == [0, 1, 2]
    for method, params, most in [("two", [1, 2, None], 2), ("none", [1, 2, 3], 0)]:
        assert dispatcher.answer(call(method, params))["error"] == {
            "code": INVALID_PARAMS,
            "message": f"too many arguments, want at most {most}",
        }
    assert ran == [[], [1], [1, None]]


def test_every_embedded_method_refuses_too_many_parameters_before_reading_the_chain() -> None:
    """Both tables, the threaded one and the one answered on the event loop, are bounded: a
    method's handler that read a parameter or the chain here would fail on the missing chain
    (-32603), not refuse (-32602)."""
    methods = EmbeddedMethods(cast(Any, None), cast(Any, None), cast(Any, None))
    tables = {"threaded": methods.table(), "inline": methods.inline_table()}
    for name, table in tables.items():
        dispatcher = Dispatcher(table)
        for method in table:
            error = dispatcher.answer(call(method, [None] * 8))["error"]
            assert error["code"] == INVALID_PARAMS, (name, method, error)
            assert error["message"].startswith("too many arguments, want at most "), error
    assert {"eth_call", "eth_getTransactionReceipt", "eth_chainId"} <= set(tables["inline"])
