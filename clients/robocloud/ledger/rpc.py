"""A minimal Ethereum JSON-RPC 2.0 client over httpx.

The SDK talks to the chain only through standard JSON-RPC, so the same code works against the
ledger service's ``/rpc`` and against any Ethereum node. Revert data in error objects is
recognised in the shapes nodes actually use: geth, anvil and hardhat put the ABI-encoded reason
in ``error.data`` (a hex string, sometimes nested as ``{"data": hex}``), others only in the
message (``execution reverted: <reason>``).
"""

from __future__ import annotations

import itertools
from typing import Any

import httpx

from robocloud.client import USER_AGENT, raise_for_error
from robocloud.ledger.abi import ContractAbi, decode_revert
from robocloud.ledger.errors import RevertError, RpcError

REVERT_PREFIX = "execution reverted"


def _hex_data(data: Any) -> bytes | None:
    """Revert bytes from an error's ``data`` field, whichever nesting the node used."""
    if isinstance(data, dict):
        data = data.get("data") or data.get("result")
    if isinstance(data, str) and data.startswith("0x"):
        try:
            return bytes.fromhex(data[2:])
        except ValueError:
            return None
    return None


def as_revert(error: RpcError, contracts: list[ContractAbi]) -> RevertError | None:
    """The ``RevertError`` an RPC error stands for, or None when it is not a revert."""
    data = _hex_data(error.data)
    if data is not None and (error.code == 3 or REVERT_PREFIX in error.message.lower()):
        return RevertError(decode_revert(data, contracts), data=data)
    lowered = error.message.lower()
    if REVERT_PREFIX in lowered:
        reason = error.message[lowered.index(REVERT_PREFIX) + len(REVERT_PREFIX) :]
        reason = reason.lstrip(":").strip()
        return RevertError(reason or "execution reverted without a reason")
    return None


class JsonRpcClient:
    """Sends JSON-RPC requests to one endpoint; raises ``RpcError`` on JSON-RPC errors."""

    def __init__(
        self,
        url: str,
        *,
        timeout: float = 30.0,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.url = url
        self._ids = itertools.count(1)
        self._http = httpx.Client(
            timeout=timeout, transport=transport, headers={"User-Agent": USER_AGENT}
        )

    def __enter__(self) -> JsonRpcClient:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def request(self, method: str, params: list[Any] | None = None) -> Any:
        """The ``result`` of one call.

        An HTTP error status carrying a JSON-RPC error object is still an ``RpcError``; one
        carrying the services' JSON error model is the SDK's typed ``ApiError``.
        """
        payload = {"jsonrpc": "2.0", "id": next(self._ids), "method": method, "params": params}
        response = self._http.post(self.url, json=payload)
        try:
            body = response.json()
        except ValueError:
            body = None
        error = body.get("error") if isinstance(body, dict) else None
        if isinstance(error, dict) and isinstance(error.get("code"), int):
            raise RpcError(
                method, int(error["code"]), str(error.get("message", "")), error.get("data")
            )
        raise_for_error(response)
        if not isinstance(body, dict) or "result" not in body:
            raise RpcError(method, -32603, f"malformed JSON-RPC response from {self.url}")
        return body["result"]
