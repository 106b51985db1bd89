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
from eth_utils.crypto import keccak

from robocloud.client import BaseClient, api_error
from robocloud.errors import InvalidAnswerError, RobocloudError
from robocloud.ledger.abi import ContractAbi, decode_revert
from robocloud.ledger.errors import RevertError, RpcError

REVERT_PREFIX = "execution reverted"
SEND_RAW_TRANSACTION = "eth_sendRawTransaction"
READ_METHODS = frozenset(
    {
        "eth_blockNumber",
        "eth_call",
        "eth_chainId",
        "eth_estimateGas",
        "eth_feeHistory",
        "eth_gasPrice",
        "eth_getBalance",
        "eth_getBlockByHash",
        "eth_getBlockByNumber",
        "eth_getCode",
        "eth_getLogs",
        "eth_getStorageAt",
        "eth_getTransactionByHash",
        "eth_getTransactionCount",
        "eth_getTransactionReceipt",
        "eth_maxPriorityFeePerGas",
        "eth_syncing",
        "net_listening",
        "net_version",
        "web3_clientVersion",
    }
)
"""Methods that only read chain state: resending one after a broken exchange changes nothing."""


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


class JsonRpcClient(BaseClient):
    """Sends JSON-RPC requests to one endpoint; raises ``RpcError`` on JSON-RPC errors.

    Retries follow the base client's policy, told per method whether a resend is safe. Every
    method in ``READ_METHODS`` only reads, so a broken exchange is retried like a GET.
    ``eth_sendRawTransaction`` is retried too, because what is resent is the same signed bytes:
    one transaction, one hash, one nonce, so a node includes it at most once however often it
    arrives. A resend can only change the *answer*: a node that kept the first copy says
    "already known", or "nonce too low" once it is mined. So when a resent
    ``eth_sendRawTransaction`` is refused, the client asks for the transaction by its hash and,
    if the node has it, answers that hash as a first send would have. Every other method (above
    all ``eth_sendTransaction``, where the node signs each copy anew with a fresh nonce) is
    retried only when the connection failed and nothing was sent.
    """

    def __init__(
        self,
        url: str,
        *,
        service: str | None = None,
        timeout: float = 30.0,
        retries: int = 3,
        backoff_s: float = 0.2,
        transport: httpx.BaseTransport | None = None,
        deployment: str | None = None,
    ) -> None:
        super().__init__(
            url,
            service=service,
            timeout=timeout,
            retries=retries,
            backoff_s=backoff_s,
            transport=transport,
            deployment=deployment,
        )
        self.url = self.base_url
        self._ids = itertools.count(1)

    def request(self, method: str, params: list[Any] | None = None) -> Any:
        """The ``result`` of one call.

        An HTTP error status carrying a JSON-RPC error object is still an ``RpcError``; one
        carrying the services' JSON error model is the SDK's typed ``ApiError``; an answer that
        is not JSON-RPC (or is nested past the bound) is an ``InvalidAnswerError``.
        """
        request_id = next(self._ids)
        payload = {"jsonrpc": "2.0", "id": request_id, "method": method, "params": params}
        resend_is_safe = method in READ_METHODS or method == SEND_RAW_TRANSACTION
        response, attempts = self._send_counting(
            "POST", self.url, json=payload, signed=False, idempotent=resend_is_safe
        )
        try:
            return self._result(method, request_id, response)
        except RpcError:
            if method != SEND_RAW_TRANSACTION or attempts == 1:
                raise
            tx_hash = self._known_transaction(params)
            if tx_hash is None:
                raise
            return tx_hash

    def _known_transaction(self, params: list[Any] | None) -> str | None:
        """The hash of the raw transaction in ``params`` if the node already has it."""
        try:
            tx_hash = "0x" + keccak(hexstr=str((params or [""])[0])).hex()
            known = self.request("eth_getTransactionByHash", [tx_hash])
        except (RobocloudError, ValueError):
            return None
        return tx_hash if known is not None else None

    def _result(self, method: str, request_id: int, response: httpx.Response) -> Any:
        if 300 <= response.status_code < 400:
            self.raise_for_status(response)
        try:
            body = self.json_of(response)
        except InvalidAnswerError:
            if response.status_code >= 400:
                raise api_error(response) from None
            raise
        error = body.get("error") if isinstance(body, dict) else None
        if isinstance(error, dict) and isinstance(error.get("code"), int):
            raise RpcError(
                method,
                int(error["code"]),
                str(error.get("message", "")),
                error.get("data"),
                status=response.status_code,
                request_id=response.headers.get("x-request-id"),
            )
        if response.status_code >= 400:
            raise api_error(response)
        if not isinstance(body, dict) or "result" not in body or body.get("id") != request_id:
            raise self._invalid(response, f"an answer to {method} that is not JSON-RPC 2.0")
        return body["result"]
