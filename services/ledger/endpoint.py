"""Where each ``/rpc`` request runs: on the event loop, on a worker thread, or in a call slot.

A call (``eth_call``, ``eth_estimateGas``, ``eth_createAccessList``) runs EVM code for free,
up to the EVM timeout of CPU each (``rpc.COSTLY_METHODS`` also counts ``eth_feeHistory``).
Under the GIL every such call on a worker thread takes its share of the one core that also
serves HTTP and mines, and the worker threads are shared with transactions. Sixty looping
calls at once used to take all forty worker threads and so much of the GIL that a transaction
or a balance read waited past thirty seconds.

So calls run in a few slots (``ledger_rpc_max_calls``), waited for on the event loop, where
waiting costs no thread; a call that finds no slot within the EVM timeout is refused with
``limit exceeded`` (-32005), and the threads stay free for everything else. The inline
``eth_call`` at the head (see ``rpc.EmbeddedMethods.head_call``) is tried on the event loop
only while no call holds a slot: under a flood of slow calls each would hold the loop for
its budget first.
"""

from __future__ import annotations

from typing import Any

import anyio

from services.ledger.rpc import (
    INLINE_MAX_BYTES,
    LIMIT_EXCEEDED,
    NOT_INLINE,
    Dispatcher,
    RpcFailure,
    error_answer,
)


class RpcEndpoint:
    """Answers ``/rpc`` bodies with ``dispatcher``, its costly requests ``slots`` at a time."""

    def __init__(self, dispatcher: Dispatcher, slots: int, slot_wait_s: float) -> None:
        self.dispatcher = dispatcher
        self.slot_wait_s = slot_wait_s
        self._slots = anyio.CapacityLimiter(slots)

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
        if small and (not costly or self._slots.borrowed_tokens == 0):
            answer = self.dispatcher.answer_inline(document)
            if answer is not NOT_INLINE:
                return answer
        if not costly:
            return await anyio.to_thread.run_sync(self.dispatcher.answer, document)
        try:
            with anyio.fail_after(self.slot_wait_s):
                await self._slots.acquire()
        except TimeoutError:
            return self._refusal(document)
        try:
            return await anyio.to_thread.run_sync(self.dispatcher.answer, document)
        finally:
            self._slots.release()

    def _refusal(self, document: Any) -> Any:
        slots = int(self._slots.total_tokens)
        failure = RpcFailure(
            LIMIT_EXCEEDED,
            f"limit exceeded: all {slots} call slots stayed busy for {self.slot_wait_s:g} s; "
            "retry later",
        )
        return self.dispatcher.refusal(document, failure)
