"""Where each ``/rpc`` request runs: on the event loop, on a worker thread, or in a call slot.

The costly methods (``rpc.COSTLY_METHODS``: calls that run EVM code up to the EVM timeout,
``eth_feeHistory``) take turns in ``ledger_rpc_max_calls`` slots (``services.common.slots``);
one finding none within the EVM timeout is refused ``limit exceeded`` (-32005), as a node
refuses what is over its limits. Sixty clients looping ``eth_call`` used to take all forty
worker threads and so much of the GIL that a transaction waited 20 s. The inline ``eth_call``
at the head (``rpc.EmbeddedMethods.head_call``) is tried on the event loop only while no slot
is busy: under a flood of slow calls each would first hold the loop for its budget.

In external-node mode a ``forwarding.NodeForwarder`` relays the calls instead, from the event
loop; the costly ones still take turns in the slots.
"""

from __future__ import annotations

from typing import Any

import anyio

from services.common.slots import Slots, SlotsBusy
from services.ledger.forwarding import NodeForwarder
from services.ledger.rpc import (
    INLINE_MAX_BYTES,
    LIMIT_EXCEEDED,
    NOT_INLINE,
    Call,
    Dispatcher,
    RpcFailure,
    batch_refusal,
    collect,
    error_answer,
    requests_of,
)


class RpcEndpoint:
    """Answers ``/rpc`` bodies with ``dispatcher``, or relays them with ``forwarder`` when
    there is one; the costly requests in ``slots`` either way."""

    def __init__(
        self, dispatcher: Dispatcher, slots: Slots, forwarder: NodeForwarder | None = None
    ) -> None:
        self.dispatcher = dispatcher
        self.slots = slots
        self.forwarder = forwarder

    async def answer(self, body: bytes) -> Any:
        """The response document for ``body``; None when nothing is to be answered."""
        small = len(body) <= INLINE_MAX_BYTES
        try:
            if small:
                document = self.dispatcher.parse(body)
            else:
                document = await anyio.to_thread.run_sync(self.dispatcher.parse, body)
        except RpcFailure as failure:
            return error_answer(None, failure)
        costly = self.dispatcher.costly(document)
        if self.forwarder is not None:
            return await self._relayed(self.forwarder, document, costly)
        if small and (not costly or self.slots.idle):
            answer = self.dispatcher.answer_inline(document)
            if answer is not NOT_INLINE:
                return answer
        if not costly:
            return await anyio.to_thread.run_sync(self.dispatcher.answer, document)
        try:
            return await self.slots.run_sync(lambda: self.dispatcher.answer(document))
        except SlotsBusy as busy:
            return self._refusal(document, busy)

    async def _relayed(self, forwarder: NodeForwarder, document: Any, costly: bool) -> Any:
        if isinstance(document, list) and (refused := batch_refusal(document)) is not None:
            return refused
        framed = [self.dispatcher.frame(item) for item in requests_of(document)]
        calls = [call for call in framed if isinstance(call, Call)]
        try:
            outcomes = iter((await self._relay(forwarder, calls, costly)) if calls else [])
        except SlotsBusy as busy:
            return self._refusal(document, busy)
        answers = [
            _answer(item, next(outcomes)) if isinstance(item, Call) else item for item in framed
        ]
        return collect(document, answers)

    async def _relay(self, forwarder: NodeForwarder, calls: list[Call], costly: bool) -> list[Any]:
        if not costly:
            return await forwarder.relay(calls)
        async with self.slots.turn():
            return await forwarder.relay(calls, costly=True)

    def _refusal(self, document: Any, busy: SlotsBusy) -> Any:
        return self.dispatcher.refusal(
            document, RpcFailure(LIMIT_EXCEEDED, f"limit exceeded: {busy}")
        )


def _answer(call: Call, outcome: Any) -> dict[str, Any] | None:
    return call.failed(outcome) if isinstance(outcome, RpcFailure) else call.answered(outcome)
