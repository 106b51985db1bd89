"""Where each ``/rpc`` request runs: on the event loop, on a worker thread, or in a call slot.

The costly methods (``rpc.COSTLY_METHODS``: calls that run EVM code up to the EVM timeout,
``eth_feeHistory``) take turns in ``ledger_rpc_max_calls`` slots (``services.common.slots``);
one finding none within the EVM timeout is refused ``limit exceeded`` (-32005), as a node
refuses what is over its limits. Sixty clients looping ``eth_call`` used to take all forty
worker threads and so much of the GIL that a transaction waited 20 s. The inline ``eth_call``
at the head (``rpc.EmbeddedMethods.head_call``) is tried on the event loop only while no slot
is busy: under a flood of slow calls each would first hold the loop for its budget.
"""

from __future__ import annotations

from typing import Any

import anyio

from services.common.slots import Slots, SlotsBusy
from services.ledger.rpc import (
    INLINE_MAX_BYTES,
    LIMIT_EXCEEDED,
    NOT_INLINE,
    Dispatcher,
    RpcFailure,
    error_answer,
)


class RpcEndpoint:
    """Answers ``/rpc`` bodies with ``dispatcher``, its costly requests in ``slots``."""

    def __init__(self, dispatcher: Dispatcher, slots: Slots) -> None:
        self.dispatcher = dispatcher
        self.slots = slots

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
        if small and (not costly or self.slots.idle):
            answer = self.dispatcher.answer_inline(document)
            if answer is not NOT_INLINE:
                return answer
        if not costly:
            return await anyio.to_thread.run_sync(self.dispatcher.answer, document)
        try:
            return await self.slots.run_sync(lambda: self.dispatcher.answer(document))
        except SlotsBusy as busy:
            refusal = RpcFailure(LIMIT_EXCEEDED, f"limit exceeded: {busy}")
            return self.dispatcher.refusal(document, refusal)
