"""Where /rpc requests run: calls take turns in a few slots, nothing else waits for them."""

from __future__ import annotations

import json
import threading
from typing import Any

import anyio

from services.common.slots import Slots
from services.ledger.endpoint import RpcEndpoint
from services.ledger.rpc import LIMIT_EXCEEDED, Dispatcher, NotInline

REFUSAL = {
    "code": LIMIT_EXCEEDED,
    "message": "limit exceeded: all 1 call slots stayed busy for 0.2 s; retry later",
}


class Methods:
    """A costly ``call`` that runs until released, and a cheap ``read``."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.inline_calls = 0

    def call(self, params: list[Any]) -> Any:
        self.release.wait(10)
        return "called"

    def inline_call(self, params: list[Any]) -> Any:
        self.inline_calls += 1
        raise NotInline()

    def endpoint(self) -> RpcEndpoint:
        dispatcher = Dispatcher(
            {"call": self.call, "read": lambda _: "read"},
            inline={"call": self.inline_call},
            costly=["call"],
        )
        return RpcEndpoint(dispatcher, Slots("call", 1, 0.2))


def body(method: str, request_id: int | None = 1) -> bytes:
    request: dict[str, Any] = {"jsonrpc": "2.0", "method": method, "params": []}
    if request_id is not None:
        request["id"] = request_id
    return json.dumps(request).encode()


def while_a_call_holds_the_slot(methods: Methods, *bodies: bytes) -> list[Any]:
    """The answers to ``bodies``, each sent while a first call runs in the only slot."""
    endpoint = methods.endpoint()
    answers: list[Any] = []

    async def scenario() -> None:
        async with anyio.create_task_group() as tasks:
            tasks.start_soon(endpoint.answer, body("call"))
            await anyio.sleep(0.05)
            for each in bodies:
                answers.append(await endpoint.answer(each))
            methods.release.set()

    anyio.run(scenario)
    return answers


def test_a_call_finding_no_slot_is_refused_and_a_read_still_answered() -> None:
    methods = Methods()
    answers = while_a_call_holds_the_slot(methods, body("call", 2), body("read", 3))
    assert answers == [
        {"jsonrpc": "2.0", "id": 2, "error": REFUSAL},
        {"jsonrpc": "2.0", "id": 3, "result": "read"},
    ]


def test_a_batch_with_a_call_is_refused_whole_and_a_notification_silently() -> None:
    methods = Methods()
    batch = json.dumps([json.loads(body("read", 4)), json.loads(body("call", 5))]).encode()
    answers = while_a_call_holds_the_slot(methods, batch, body("call", None))
    assert answers == [{"jsonrpc": "2.0", "id": None, "error": REFUSAL}, None]


def test_the_inline_attempt_waits_for_idle_slots() -> None:
    """Under a flood of slow calls each would hold the event loop for its budget first."""
    methods = Methods()
    while_a_call_holds_the_slot(methods, body("call", 2))
    assert methods.inline_calls == 1  # the first call's, made while the slot was free


def test_a_call_is_answered_once_the_slot_frees() -> None:
    methods = Methods()
    methods.release.set()
    endpoint = methods.endpoint()
    assert anyio.run(endpoint.answer, body("call", 6)) == {
        "jsonrpc": "2.0",
        "id": 6,
        "result": "called",
    }
