"""External-node mode's ``/rpc``: requests relayed to the node from the event loop.

A relayed request waits for as long as the node takes, and a node lets a call run for as long
as its own limits say (anvil: until the gas runs out). Relayed from worker threads, sixty
clients looping ``eth_call`` held all forty of them, and the readiness probe, the index and
every REST read queued behind (``/readyz`` went 503). Here a relayed request holds no thread,
only one of ``max_connections`` connections to the node; the costly methods also take turns
in the call slots, as on the embedded chain, and the node gets the EVM timeout to answer them.

The framing is the dispatcher's, so a malformed request gets the same answer in either mode;
well-framed calls of the standard namespaces go to the node together (a batch stays a batch)
and its answers are matched back by id, every error relayed unchanged.
"""

from __future__ import annotations

import logging
from typing import Any

import httpx

from robocloud import bounded_json
from services.ledger.rpc import (
    INTERNAL_ERROR,
    LIMIT_EXCEEDED,
    METHOD_NOT_FOUND,
    REQUEST_TIMED_OUT,
    Call,
    RpcFailure,
)

log = logging.getLogger("robocloud.ledger.forwarding")

FORWARDED_PREFIXES = ("eth_", "net_", "web3_")
"""The standard namespaces; a node's ``anvil_*``, ``debug_*`` or ``personal_*`` stay private."""
FORWARD_TIMEOUT_S = 30.0
"""How long the node may take to answer anything but the costly methods (the SDK's timeout)."""
CONNECTION_WAIT_S = 5.0

Outcome = Any
"""A call's result, or the ``RpcFailure`` to answer it with."""


def not_forwarded(method: str) -> RpcFailure | None:
    """The refusal of a method outside the standard namespaces; None to forward it."""
    if method.startswith(FORWARDED_PREFIXES):
        return None
    return RpcFailure(METHOD_NOT_FOUND, f"the method {method} does not exist/is not available")


class NodeForwarder:
    """Relays calls to the node at ``url`` over at most ``max_connections`` connections; the
    node has ``call_timeout_s`` to answer costly ones, ``FORWARD_TIMEOUT_S`` the others."""

    def __init__(
        self,
        url: str,
        max_connections: int,
        call_timeout_s: float,
        connection_wait_s: float = CONNECTION_WAIT_S,
    ) -> None:
        self.max_connections = max_connections
        self.call_timeout_s = call_timeout_s
        self.connection_wait_s = connection_wait_s
        self._client = httpx.AsyncClient(
            base_url=url,
            limits=httpx.Limits(
                max_connections=max_connections, max_keepalive_connections=max_connections
            ),
            timeout=httpx.Timeout(FORWARD_TIMEOUT_S, pool=connection_wait_s),
        )

    async def relay(self, calls: list[Call], *, costly: bool = False) -> list[Outcome]:
        """The outcome of each call, in order; the standard ones go in one exchange."""
        refusals = [not_forwarded(call.method) for call in calls]
        sent = [call for call, refusal in zip(calls, refusals, strict=True) if refusal is None]
        timeout_s = self.call_timeout_s if costly else FORWARD_TIMEOUT_S
        outcomes = iter(await self._exchange(sent, timeout_s) if sent else [])
        return [refusal or next(outcomes) for refusal in refusals]

    async def _exchange(self, calls: list[Call], timeout_s: float) -> list[Outcome]:
        requests = [
            {"jsonrpc": "2.0", "id": number, "method": call.method, "params": call.params}
            for number, call in enumerate(calls)
        ]
        timeout = httpx.Timeout(timeout_s, pool=self.connection_wait_s)
        try:
            response = await self._client.post(
                "", json=requests if len(requests) > 1 else requests[0], timeout=timeout
            )
            return _outcomes(response, len(calls))
        except httpx.PoolTimeout:
            failure = RpcFailure(
                LIMIT_EXCEEDED,
                f"limit exceeded: all {self.max_connections} connections to the node stayed "
                f"busy for {self.connection_wait_s:g} s; retry later",
            )
        except httpx.TimeoutException:
            failure = RpcFailure(REQUEST_TIMED_OUT, "request timed out")
        except httpx.HTTPError as exc:
            log.warning("the node did not answer", extra={"error": repr(exc)})
            failure = RpcFailure(INTERNAL_ERROR, "the Ethereum node did not answer")
        return [failure] * len(calls)

    async def aclose(self) -> None:
        await self._client.aclose()


def _outcomes(response: httpx.Response, count: int) -> list[Outcome]:
    """The node's answers to requests numbered 0 to ``count - 1``, each one's result or error;
    an answer the node did not give is an internal error."""
    try:
        document = bounded_json.loads(response.content)
    except bounded_json.JsonError:
        document = None
    answers = document if isinstance(document, list) else [document]
    if len(answers) == 1 and _error(answers[0]) is not None and answers[0].get("id") is None:
        return [_error(answers[0])] * count
    by_id = {answer.get("id"): answer for answer in answers if isinstance(answer, dict)}
    outcomes: list[Outcome] = []
    for number in range(count):
        answer = by_id.get(number)
        failure = _error(answer)
        if failure is not None:
            outcomes.append(failure)
        elif isinstance(answer, dict) and "result" in answer:
            outcomes.append(answer["result"])
        else:
            log.warning(
                "the node gave no answer to a request", extra={"status": response.status_code}
            )
            outcomes.append(RpcFailure(INTERNAL_ERROR, "the Ethereum node gave no answer"))
    return outcomes


def _error(answer: Any) -> RpcFailure | None:
    """The JSON-RPC error object in ``answer``, as the failure to relay unchanged."""
    error = answer.get("error") if isinstance(answer, dict) else None
    if not isinstance(error, dict) or not isinstance(error.get("code"), int):
        return None
    return RpcFailure(int(error["code"]), str(error.get("message", "")), error.get("data"))
