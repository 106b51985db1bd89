"""Ethereum JSON-RPC 2.0 over the embedded chain: the dispatcher and the method table.

``Dispatcher`` speaks the JSON-RPC 2.0 envelope (single calls, batches, notifications, the
standard error codes) and knows nothing about Ethereum; ``EmbeddedMethods`` implements the
``eth_*`` methods web3.py, ethers and the SDK use, over ``EmbeddedChain`` and the event index.
Refusals are JSON-RPC error objects shaped like geth's, so clients need no special casing:
a revert is code 3 with the revert bytes in ``data`` and ``execution reverted: <reason>``.
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any

from eth.abc import BlockAPI
from eth_utils.address import is_hex_address
from eth_utils.crypto import keccak

import robocloud
from robocloud import bounded_json
from services.common.slots import client_var
from services.ledger import encoding, fees
from services.ledger.calls import OverBudget
from services.ledger.chain import (
    HEAD_TAGS,
    BlockTag,
    CallRequest,
    ChainError,
    EmbeddedChain,
    InvalidParams,
)
from services.ledger.filters import MAX_OPTIONS, MAX_TOPICS, Filters, LogCriteria
from services.ledger.index import EventIndex, IndexLimitError

log = logging.getLogger("robocloud.ledger.rpc")

PARSE_ERROR = -32700
INVALID_REQUEST = -32600
METHOD_NOT_FOUND = -32601
INVALID_PARAMS = -32602
INTERNAL_ERROR = -32603
MAX_BATCH = 100
MAX_DEPTH = 32
"""Ethereum requests nest a handful of levels (a filter's topic lists are the deepest)."""
MAX_ID_LENGTH = 128
PRIORITY_FEE_WEI = 10**9
NAMED_TAGS = ("latest", "pending", "earliest", "safe", "finalized")
MAX_FEE_HISTORY_BLOCKS = 1024
MAX_PERCENTILES = 100
PROTOCOL_VERSION = 68
QUANTITY = re.compile(r"0[xX][0-9a-fA-F]+")
SLOT = re.compile(r"0[xX][0-9a-fA-F]{0,64}")
DECIMAL = re.compile(r"[0-9]{1,20}")
BLOCK_HASH_LENGTH = 66
"""A 32-byte block hash as a string: where geth takes a block number or hash (EIP-1898),
``0x`` and 64 hex digits is a hash, never a number (anvil reads it so too)."""
"""eth/68, the wire protocol geth answered ``eth_protocolVersion`` with."""

Method = Callable[[list[Any]], Any]

MAX_PARAMS: dict[str, int] = {
    # geth's signatures (its context.Context is no parameter); every method takes at most
    # what geth's takes, so a request geth answers is answered here too
    "web3_clientVersion": 0,
    "web3_sha3": 1,
    "net_version": 0,
    "net_listening": 0,
    "eth_chainId": 0,
    "eth_protocolVersion": 0,  # removed from geth (1.10), zero parameters while it was there
    "eth_syncing": 0,
    "eth_mining": 0,  # removed from geth 1.14 (and anvil), zero parameters before
    "eth_coinbase": 0,  # removed from geth 1.14, zero parameters before
    "eth_accounts": 0,
    "eth_blockNumber": 0,
    "eth_gasPrice": 0,
    "eth_maxPriorityFeePerGas": 0,
    "eth_feeHistory": 3,  # block count, newest block, reward percentiles
    "eth_getBlockByNumber": 2,  # number, full transactions flag
    "eth_getBlockByHash": 2,  # hash, full transactions flag
    "eth_getBlockTransactionCountByNumber": 1,
    "eth_getBlockTransactionCountByHash": 1,
    "eth_getBlockReceipts": 1,
    "eth_getTransactionByHash": 1,
    "eth_getTransactionReceipt": 1,
    "eth_getTransactionByBlockNumberAndIndex": 2,
    "eth_getTransactionByBlockHashAndIndex": 2,
    "eth_getBalance": 2,  # address, block
    "eth_getTransactionCount": 2,  # address, block
    "eth_getCode": 2,  # address, block
    "eth_getStorageAt": 3,  # address, slot, block
    "eth_call": 4,  # call, block, state override, block overrides (refused unless empty)
    "eth_estimateGas": 4,  # call, block, state override, block overrides (refused unless empty)
    "eth_createAccessList": 3,  # call, block, state override (refused unless empty)
    "eth_sendRawTransaction": 1,
    "eth_getLogs": 1,
    "eth_newFilter": 1,
    "eth_newBlockFilter": 0,
    "eth_getFilterChanges": 1,
    "eth_getFilterLogs": 1,
    "eth_uninstallFilter": 1,
}
"""How many positional parameters each method takes at most, as geth's signature of it has
(``internal/ethapi/api.go``, ``eth/filters/api.go``, ``node/api.go``): one more is -32602.
The overrides geth takes after a call's block are counted (web3.py sends a state override
third when given one); the embedded chain cannot apply them, so one that asks for something is
refused (``without_overrides``)."""


class RpcFailure(Exception):
    """A JSON-RPC error object to answer with."""

    def __init__(self, code: int, message: str, data: Any = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.data = data

    def to_json(self) -> dict[str, Any]:
        error: dict[str, Any] = {"code": self.code, "message": self.message}
        if self.data is not None:
            error["data"] = self.data
        return error


def at_most(limit: int, method: Method) -> Method:
    """``method`` refusing more than ``limit`` positional parameters before it reads any, as
    geth refuses them (-32602 ``too many arguments, want at most N``, a null counted as any
    other value; anvil refuses them too). Each method read the parameters it knew and dropped
    the rest, so ``eth_chainId`` with ``[1, 2, 3]`` answered the chain id, and
    ``eth_getBalance`` with ``[address, "latest", "x"]`` a balance, as if ``"x"`` was never
    sent: a caller's mistake passed for an answer."""

    def checked(params: list[Any]) -> Any:
        if len(params) > limit:
            raise RpcFailure(INVALID_PARAMS, f"too many arguments, want at most {limit}")
        return method(params)

    return checked


OVERRIDABLE = frozenset({"eth_call", "eth_estimateGas", "eth_createAccessList"})
"""Methods that take geth's state override (and block overrides) after their block."""


def without_overrides(method: Method) -> Method:
    """``method`` refusing a state or block override that asks for something (-32602): the
    embedded chain cannot apply one, and an answer computed without the override a caller
    sent is another call's answer passed for its own. A null or empty one asks nothing."""

    def checked(params: list[Any]) -> Any:
        if any(value is not None and value != {} for value in params[2:]):
            raise RpcFailure(
                INVALID_PARAMS, "state and block overrides are not supported by this node"
            )
        return method(params)

    return checked


def bounded(methods: Mapping[str, Method]) -> dict[str, Method]:
    """``methods``, each refusing more parameters than ``MAX_PARAMS`` gives it (and the
    overridable ones an override): a method with no entry there is a ``KeyError`` when the
    table is built, never a method that takes any number of parameters."""
    return {
        name: at_most(
            MAX_PARAMS[name], without_overrides(method) if name in OVERRIDABLE else method
        )
        for name, method in methods.items()
    }


class UnknownBlock(ChainError):
    """A block parameter names a hash the chain does not hold."""


class NotInline(Exception):
    """An inline method cannot answer without blocking: run the request on a worker thread."""


NOT_INLINE = object()
INLINE_MAX_BYTES = 4096
INLINE_CALL_BUDGET_S = 0.005
"""How long an ``eth_call`` may hold the event loop before it is handed to a worker thread."""
REQUEST_TIMED_OUT = -32002
RESPONSE_TOO_LARGE = -32003
LIMIT_EXCEEDED = -32005
MAX_BATCH_RESPONSE_BYTES = 25_000_000
"""geth's ``--rpc.batch-response-max-size``: once a batch's answers pass it, the calls left
are answered -32003 ``response too large`` without being run. 100 ``eth_getLogs`` of a block
of 10,000 logs, a 9 KB request, answered 142 MB and took the service to 650 MB."""
COSTLY_METHODS = frozenset(
    {"eth_call", "eth_estimateGas", "eth_createAccessList", "eth_feeHistory"}
)
"""Methods a caller does not pay for that may take much CPU: the three run EVM code (up to the
EVM timeout each); ``eth_feeHistory`` with reward percentiles reads the receipts of up to 1,024
blocks (0.56 s on the development machine)."""


@dataclass(frozen=True)
class EncodedBatch:
    """A batch's answers, each encoded as JSON when it was made, so that a batch holds bytes
    it has counted rather than every result's objects at once."""

    parts: tuple[bytes, ...]

    def body(self) -> bytes:
        return b"[" + b",".join(self.parts) + b"]"


def encode(answer: Any) -> bytes:
    """One answer as the service sends JSON (Starlette's ``JSONResponse`` settings)."""
    return json.dumps(answer, ensure_ascii=False, allow_nan=False, separators=(",", ":")).encode()


@dataclass(frozen=True)
class Call:
    """One well-framed request: the method to run and how to answer it."""

    request_id: Any
    method: str
    params: list[Any]
    notification: bool
    """Sent without an id: run, but never answered."""

    def answered(self, result: Any) -> dict[str, Any] | None:
        if self.notification:
            return None
        return {"jsonrpc": "2.0", "id": self.request_id, "result": result}

    def failed(self, failure: RpcFailure) -> dict[str, Any] | None:
        return None if self.notification else error_answer(self.request_id, failure)


class Dispatcher:
    """JSON-RPC 2.0 framing over a table of methods taking positional parameters."""

    def __init__(
        self,
        methods: Mapping[str, Method],
        fallback: Callable[[str, list[Any]], Any] | None = None,
        inline: Mapping[str, Method] | None = None,
        costly: Iterable[str] = (),
        batch_timeout_s: float | None = None,
        batch_response_max_bytes: int = MAX_BATCH_RESPONSE_BYTES,
    ) -> None:
        """``fallback`` answers methods not in the table (a proxy to an external node);
        ``inline`` are versions of some methods that never block (no lock, no disk, no
        unbounded work), which may raise ``NotInline`` to hand the request to a thread;
        ``costly`` names the methods whose requests the caller must admit sparingly (see
        ``endpoint``); a batch starts no call after ``batch_timeout_s``, as geth's batches
        answer the calls left when its timeout fires with ``request timed out``, and none
        after its answers pass ``batch_response_max_bytes`` (geth's
        ``--rpc.batch-response-max-size``)."""
        self.methods = dict(methods)
        self.fallback = fallback
        self.inline = dict(inline or {})
        self.costly_methods = frozenset(costly)
        self.batch_timeout_s = batch_timeout_s
        self.batch_response_max_bytes = batch_response_max_bytes

    def parse(self, body: bytes) -> Any:
        """The request document of ``body``; ``RpcFailure`` when it is none (answered with a
        null id: there is no request to take an id from)."""
        try:
            return bounded_json.loads(body, max_depth=MAX_DEPTH)
        except (bounded_json.JsonNumberError, bounded_json.JsonDepthError) as exc:
            raise RpcFailure(INVALID_REQUEST, f"invalid request: {exc}") from exc
        except bounded_json.JsonError as exc:
            raise RpcFailure(PARSE_ERROR, f"parse error: {exc}") from exc

    def costly(self, document: Any) -> bool:
        """Whether ``document`` (one call or a batch) asks for any costly method."""
        return any(_method(request) in self.costly_methods for request in requests_of(document))

    def answer_inline(self, document: Any) -> Any:
        """The answer to a single call of an inline method, computed on the caller's thread
        (the event loop: a worker thread costs a quarter of a millisecond per request);
        ``NOT_INLINE`` for everything else, which ``answer`` then answers."""
        if _method(document) not in self.inline:
            return NOT_INLINE
        try:
            return self._one(document, self.inline)
        except NotInline:
            return NOT_INLINE

    def handle(self, body: bytes) -> Any:
        """The response document for a request body (a batch's as an ``EncodedBatch``);
        None when nothing is to be answered."""
        try:
            document = self.parse(body)
        except RpcFailure as failure:
            return error_answer(None, failure)
        return self.answer(document)

    def answer(self, document: Any) -> Any:
        """The response document for a parsed request, a batch's as an ``EncodedBatch``;
        None when nothing is to be answered. A batch starts no call once its deadline has
        passed (``request timed out``) or once its answers hold more than
        ``batch_response_max_bytes`` (``response too large``), as geth answers the calls
        left: the call that passed the bound is answered whole, as in geth."""
        if not isinstance(document, list):
            return self._one(document)
        refused = batch_refusal(document)
        if refused is not None:
            return refused
        deadline = None if self.batch_timeout_s is None else time.monotonic() + self.batch_timeout_s
        parts: list[bytes] = []
        size = 0
        for item in document:
            if size > self.batch_response_max_bytes:
                left: RpcFailure | None = RpcFailure(RESPONSE_TOO_LARGE, "response too large")
            elif deadline is not None and time.monotonic() > deadline:
                left = RpcFailure(REQUEST_TIMED_OUT, "request timed out")
            else:
                left = None
            answer = self._one(item, unrun=left)
            if answer is not None:
                parts.append(encode(answer))
                size += len(parts[-1])
        return EncodedBatch(tuple(parts)) if parts else None

    def refusal(self, document: Any, failure: RpcFailure) -> Any:
        """``failure`` as the answer to a whole request left unrun: to a single call with its
        id (none to a notification), to a batch as one error, as a batch too large is."""
        if not isinstance(document, dict):
            return error_answer(None, failure)
        if "id" not in document:
            return None
        return error_answer(document["id"] if _valid_id(document["id"]) else None, failure)

    def frame(self, request: Any) -> Call | dict[str, Any] | None:
        """``request`` as a ``Call`` to run, or, when it is malformed, the answer to it."""
        if not isinstance(request, dict) or request.get("jsonrpc") != "2.0":
            return error_answer(None, RpcFailure(INVALID_REQUEST, "not a JSON-RPC 2.0 request"))
        request_id = request.get("id")
        if not _valid_id(request_id):
            return error_answer(
                None, RpcFailure(INVALID_REQUEST, "id must be a string, a number or null")
            )
        method, params = request.get("method"), request.get("params", [])
        if not isinstance(method, str) or not isinstance(params, list | dict | type(None)):
            failure = RpcFailure(INVALID_REQUEST, "method must be a string, params an array")
            return error_answer(request_id, failure)
        notification = "id" not in request
        if isinstance(params, dict):
            # Ethereum methods take positional parameters only: by-name parameters are a
            # valid request with invalid parameters (-32602), as geth and anvil answer them.
            failure = RpcFailure(
                INVALID_PARAMS, "invalid params: expected an array of positional parameters"
            )
            return Call(request_id, method, [], notification).failed(failure)
        return Call(request_id, method, params or [], notification)

    def _one(
        self,
        request: Any,
        table: Mapping[str, Method] | None = None,
        *,
        unrun: RpcFailure | None = None,
    ) -> dict[str, Any] | None:
        """The answer to one request; with ``unrun`` (its batch ran out of time or of room)
        it is framed as any other but answered ``unrun`` instead of being called."""
        call = self.frame(request)
        if not isinstance(call, Call):
            return call
        try:
            if unrun is not None:
                raise unrun
            return call.answered(self.call(call.method, call.params, table))
        except RpcFailure as failure:
            return call.failed(failure)

    def call(
        self, method: str, params: list[Any], table: Mapping[str, Method] | None = None
    ) -> Any:
        handler = (self.methods if table is None else table).get(method)
        if handler is None and self.fallback is None:
            raise RpcFailure(
                METHOD_NOT_FOUND, f"the method {method} does not exist/is not available"
            )
        try:
            if handler is None and self.fallback is not None:
                return self.fallback(method, params)
            return handler(params)  # type: ignore[misc]
        except (RpcFailure, NotInline):
            raise
        except ChainError as exc:
            raise RpcFailure(exc.code, exc.message, exc.data) from exc
        except IndexLimitError as exc:
            raise RpcFailure(LIMIT_EXCEEDED, str(exc)) from exc
        except Exception as exc:
            log.exception("JSON-RPC method failed", extra={"method": method})
            raise RpcFailure(INTERNAL_ERROR, f"internal error in {method}") from exc


def _method(request: Any) -> str | None:
    """The method a request names, if it is a request naming one (a hostile one may name a
    list, which no table can be searched for)."""
    method = request.get("method") if isinstance(request, dict) else None
    return method if isinstance(method, str) else None


def _valid_id(value: Any) -> bool:
    """JSON-RPC 2.0 ids are strings, numbers or null; ours are also bounded in length."""
    if value is None:
        return True
    if isinstance(value, bool):
        return False
    if isinstance(value, int):
        return len(str(value)) <= MAX_ID_LENGTH
    if isinstance(value, float):
        return math.isfinite(value)
    return isinstance(value, str) and len(value) <= MAX_ID_LENGTH


def error_answer(request_id: Any, failure: RpcFailure) -> dict[str, Any]:
    return {"jsonrpc": "2.0", "id": request_id, "error": failure.to_json()}


def requests_of(document: Any) -> list[Any]:
    """The requests in ``document``: a batch's, or the single call alone."""
    return document if isinstance(document, list) else [document]


def batch_refusal(batch: list[Any]) -> dict[str, Any] | None:
    """The answer to a batch too small or too large to run, as one error; None to run it."""
    if not batch:
        return error_answer(None, RpcFailure(INVALID_REQUEST, "empty batch"))
    if len(batch) > MAX_BATCH:
        return error_answer(
            None, RpcFailure(INVALID_REQUEST, f"batch of more than {MAX_BATCH} calls")
        )
    return None


def collect(document: Any, answers: list[dict[str, Any] | None]) -> Any:
    """The response document for ``document`` given one answer per request in it: a batch's
    answers without the notifications' (None when only notifications were sent)."""
    if not isinstance(document, list):
        return answers[0]
    return [answer for answer in answers if answer is not None] or None


# ----- parameters -----


def param(params: list[Any], index: int, default: Any = ...) -> Any:
    if index < len(params):
        return params[index]
    if default is ...:
        raise InvalidParams(f"missing value for required argument {index}")
    return default


def as_bytes(value: Any, what: str, length: int | None = None) -> bytes:
    if not isinstance(value, str) or not value.startswith("0x"):
        raise InvalidParams(f"invalid {what}: expected 0x-prefixed hex, got {value!r}")
    try:
        decoded = bytes.fromhex(value[2:])
    except ValueError as exc:
        raise InvalidParams(f"invalid {what}: {value!r} is not hex") from exc
    if length is not None and len(decoded) != length:
        raise InvalidParams(f"invalid {what}: expected {length} bytes, got {len(decoded)}")
    return decoded


def as_address(value: Any) -> bytes:
    if not isinstance(value, str) or not is_hex_address(value):
        raise InvalidParams(f"invalid address: {value!r}")
    return bytes.fromhex(value[2:])


def as_quantity(value: Any, what: str, bits: int = 256) -> int:
    """A quantity of at most ``bits`` bits: ``0x`` and hex digits, as geth and anvil parse
    them (anvil also takes leading zeros and ``0X``, so this does), or a JSON number.
    ``int(x, 16)`` alone also took ``0x1_0``, surrounding whitespace and non-ASCII digits."""
    if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        number = value
    elif isinstance(value, str) and QUANTITY.fullmatch(value):
        number = int(value, 16)
    else:
        raise InvalidParams(f"invalid {what}: expected a 0x-hex quantity, got {value!r}")
    if number.bit_length() > bits:
        raise InvalidParams(f"invalid {what}: {value!r} is higher than 2^{bits}-1")
    return number


def as_flag(value: Any, what: str) -> bool:
    """A boolean parameter (``eth_getBlockByNumber``'s full-transactions flag) as geth reads
    it: ``true`` or ``false``, null taken as false. ``bool(value)`` read the string
    ``"false"``, ``0`` or ``"0x0"`` as true and answered full transactions, where geth and
    anvil refuse them (-32602)."""
    if value is None:
        return False
    if not isinstance(value, bool):
        raise InvalidParams(f"invalid {what}: expected a boolean, got {value!r}")
    return value


def call_data(call: dict[str, Any]) -> Any:
    """A call object's data as geth and anvil read it: ``input``, or ``data`` where
    ``input`` is absent or null (``"0x"`` where neither is given). Reading ``input`` whenever
    the key was present ran ``{"input": null, "data": "0x.."}`` with no data at all: another
    call than the one asked, its result and gas both wrong."""
    chosen = call.get("input")
    if chosen is None:
        chosen = call.get("data")
    return chosen or "0x"


def _latest_when_unset(value: Any) -> Any:
    """A log query's bound, ``latest`` when absent or null as geth has it. ``value or
    "latest"`` also read ``fromBlock: 0`` as the head, answering only its logs, and ``""``,
    which geth and anvil refuse, as the head too."""
    return "latest" if value is None else value


def as_slot(value: Any) -> int:
    """A storage slot as geth reads one: ``0x`` and at most 64 hex digits (32 bytes)."""
    if not isinstance(value, str) or not SLOT.fullmatch(value):
        raise InvalidParams(
            f"invalid storage slot: expected 0x and at most 64 hex digits, got {value!r}"
        )
    return int(value[2:] or "0", 16)


def as_count(value: Any, what: str) -> int:
    """geth's ``HexOrDecimal64`` (``eth_feeHistory``'s block count): a quantity, or decimal
    digits, as geth and anvil take it."""
    if isinstance(value, str) and DECIMAL.fullmatch(value):
        value = int(value)
    return as_quantity(value, what, 64)


def _percentiles(value: Any) -> list[float] | None:
    """Reward percentiles as geth checks them: numbers from 0 to 100, ascending."""
    if value is None:
        return None
    if not isinstance(value, list) or len(value) > MAX_PERCENTILES:
        raise InvalidParams(f"invalid reward percentiles: at most {MAX_PERCENTILES} numbers")
    previous = 0.0
    for item in value:
        if isinstance(item, bool) or not isinstance(item, int | float):
            raise InvalidParams(f"invalid reward percentile: {item!r}")
        if not 0 <= item <= 100 or item < previous:
            raise InvalidParams(f"invalid reward percentile: {item}")
        previous = float(item)
    return [float(item) for item in value]


def _transaction_at(block: BlockAPI | None, index: int) -> Any:
    if block is None or index >= len(block.transactions):
        return None
    return encoding.transaction(block, index, block.transactions[index])


def _optional_quantity(value: dict[str, Any], key: str) -> int | None:
    return as_quantity(value[key], key) if value.get(key) is not None else None


class EmbeddedMethods:
    """The ``eth_*`` methods over the embedded chain and its event index."""

    def __init__(self, chain: EmbeddedChain, index: EventIndex, filters: Filters) -> None:
        self.chain = chain
        self.index = index
        self.filters = filters

    def table(self) -> dict[str, Method]:
        """The methods, each refusing more parameters than it takes (``MAX_PARAMS``)."""
        return bounded(self._methods())

    def _methods(self) -> dict[str, Method]:
        return {
            "web3_clientVersion": lambda _: f"robocloud-ledger/{robocloud.__version__}",
            "eth_chainId": lambda _: encoding.quantity(self.chain.chain_id),
            "net_version": lambda _: str(self.chain.chain_id),
            "net_listening": lambda _: True,
            "eth_syncing": lambda _: False,
            "eth_mining": lambda _: False,
            "eth_accounts": lambda _: [],
            "eth_blockNumber": lambda _: encoding.quantity(self.chain.head().block_number),
            "eth_gasPrice": lambda _: encoding.quantity(self.chain.base_fee() + PRIORITY_FEE_WEI),
            "eth_maxPriorityFeePerGas": lambda _: encoding.quantity(PRIORITY_FEE_WEI),
            "eth_feeHistory": self.fee_history,
            "eth_getBlockByNumber": self.block_by_number,
            "eth_getBlockByHash": self.block_by_hash,
            "eth_getTransactionByHash": self.transaction_by_hash,
            "eth_getTransactionReceipt": self.transaction_receipt,
            "eth_getBalance": self.balance,
            "eth_getTransactionCount": self.transaction_count,
            "eth_getCode": self.code,
            "eth_getStorageAt": self.storage_at,
            "eth_call": self.call,
            "eth_estimateGas": self.estimate_gas,
            "eth_sendRawTransaction": self.send_raw_transaction,
            "eth_getLogs": self.logs,
            "eth_newFilter": self.new_filter,
            "eth_newBlockFilter": self.new_block_filter,
            "eth_getFilterChanges": self.filter_changes,
            "eth_getFilterLogs": self.filter_logs,
            "eth_uninstallFilter": self.uninstall_filter,
            "eth_getBlockReceipts": self.block_receipts,
            "eth_getBlockTransactionCountByNumber": self.transaction_count_by_number,
            "eth_getBlockTransactionCountByHash": self.transaction_count_by_hash,
            "eth_getTransactionByBlockNumberAndIndex": self.transaction_by_number_and_index,
            "eth_getTransactionByBlockHashAndIndex": self.transaction_by_hash_and_index,
            "eth_createAccessList": self.create_access_list,
            "eth_coinbase": lambda _: encoding.address(self.chain.head().coinbase),
            "web3_sha3": lambda params: encoding.data(keccak(as_bytes(param(params, 0), "data"))),
            "eth_protocolVersion": lambda _: encoding.quantity(PROTOCOL_VERSION),
        }

    def inline_table(self) -> dict[str, Method]:
        """What a client asks between transactions, answered without a worker thread: none
        of these takes the chain's lock (a receipt only when its block is among the last
        mined; otherwise ``NotInline``). Only ``eth_call`` reads the disk, the state at the
        head through the calling thread's own read-only connection, which never waits for
        the writer (WAL), within ``INLINE_CALL_BUDGET_S`` once that state is built."""
        table = self._methods()
        constant = (
            "web3_clientVersion",
            "eth_chainId",
            "net_version",
            "net_listening",
            "eth_syncing",
            "eth_mining",
            "eth_accounts",
            "eth_protocolVersion",
            "eth_maxPriorityFeePerGas",
            "eth_blockNumber",
        )
        return bounded(
            {name: table[name] for name in constant}
            | {
                "eth_getTransactionReceipt": self.recent_receipt,
                "eth_getTransactionByHash": self.recent_transaction,
                "eth_call": self.head_call,
            }
        )

    def head_call(self, params: list[Any]) -> Any:
        """``eth_call`` at the head (a proof's ``rootAt``, a contract's view), tried on the
        caller's thread for at most ``INLINE_CALL_BUDGET_S``: a view call takes well under a
        millisecond, a worker thread a quarter of one more. A call at another block, or one
        that runs past the budget (abandoned, nothing of it kept), goes to a worker thread
        with the whole time limit."""
        tag = param(params, 1, "latest")
        if tag not in HEAD_TAGS:
            raise NotInline()
        request = self.call_request(param(params, 0))
        try:
            return encoding.data(self.chain.call(request, tag, INLINE_CALL_BUDGET_S))
        except OverBudget as exc:
            raise NotInline() from exc

    def recent_receipt(self, params: list[Any]) -> Any:
        tx_hash = as_bytes(param(params, 0), "transaction hash", 32)
        located = self.chain.recent(tx_hash)
        if located is None and self.chain.is_waiting(tx_hash):
            return None
        receipts = self.chain.recent_receipts(located.block.hash) if located else None
        if located is None or receipts is None:
            raise NotInline()
        return encoding.receipt(located.block, receipts, located.index, located.transaction)

    def recent_transaction(self, params: list[Any]) -> Any:
        located = self.chain.recent(as_bytes(param(params, 0), "transaction hash", 32))
        if located is None:
            raise NotInline()
        return encoding.transaction(located.block, located.index, located.transaction)

    # ----- blocks and transactions -----

    def tag(self, value: Any) -> BlockTag:
        """A block parameter where geth takes a block number or hash (state reads, calls,
        ``eth_getBlockReceipts``): a named tag, a quantity, a block hash (a string of 32
        bytes; before, ``0x00..01`` was read as block 1) or an EIP-1898 object."""
        if isinstance(value, str) and len(value) == BLOCK_HASH_LENGTH:
            value = {"blockHash": value}
        if isinstance(value, dict):
            if "blockHash" in value:
                block = self.chain.block_by_hash(as_bytes(value["blockHash"], "block hash", 32))
                if block is None:
                    raise UnknownBlock(f"block {value['blockHash']} not found")
                return int(block.number)
            value = value.get("blockNumber", "latest")
        return self.number_tag(value)

    def number_tag(self, value: Any) -> BlockTag:
        """A block parameter where geth takes a block number only (``eth_getBlockByNumber``,
        ``eth_getLogs``' range, ``eth_feeHistory``): a named tag or a quantity below 2^64."""
        if isinstance(value, str) and value in NAMED_TAGS:
            return value
        return as_quantity(value, "block number", 64)

    def block_by_number(self, params: list[Any]) -> Any:
        block = self.chain.block_by_number(self.number_tag(param(params, 0)))
        full = as_flag(param(params, 1, False), "full transactions flag")
        return encoding.block(block, full) if block is not None else None

    def block_by_hash(self, params: list[Any]) -> Any:
        block = self.chain.block_by_hash(as_bytes(param(params, 0), "block hash", 32))
        full = as_flag(param(params, 1, False), "full transactions flag")
        return encoding.block(block, full) if block is not None else None

    def transaction_by_hash(self, params: list[Any]) -> Any:
        tx_hash = as_bytes(param(params, 0), "transaction hash", 32)
        located = self.chain.locate(tx_hash)
        if located is not None:
            return encoding.transaction(located.block, located.index, located.transaction)
        waiting = self.chain.waiting(tx_hash)
        if waiting is None:
            return None
        return encoding.pending_transaction(waiting, self.chain.base_fee())

    def transaction_receipt(self, params: list[Any]) -> Any:
        located = self.chain.locate(as_bytes(param(params, 0), "transaction hash", 32))
        if located is None:
            return None
        receipts = self.chain.receipts(located.block)
        return encoding.receipt(located.block, receipts, located.index, located.transaction)

    def block_receipts(self, params: list[Any]) -> Any:
        """A block's receipts; null for a block unknown by number or by hash (geth, anvil)."""
        try:
            block = self.chain.block_by_number(self.tag(param(params, 0)))
        except UnknownBlock:
            return None
        if block is None:
            return None
        receipts = self.chain.receipts(block)
        return [
            encoding.receipt(block, receipts, index, transaction)
            for index, transaction in enumerate(block.transactions)
        ]

    def _block_by_hash_param(self, value: Any) -> BlockAPI | None:
        return self.chain.block_by_hash(as_bytes(value, "block hash", 32))

    def transaction_count_by_number(self, params: list[Any]) -> Any:
        block = self.chain.block_by_number(self.number_tag(param(params, 0)))
        return encoding.quantity(len(block.transactions)) if block is not None else None

    def transaction_count_by_hash(self, params: list[Any]) -> Any:
        block = self._block_by_hash_param(param(params, 0))
        return encoding.quantity(len(block.transactions)) if block is not None else None

    def transaction_by_number_and_index(self, params: list[Any]) -> Any:
        block = self.chain.block_by_number(self.number_tag(param(params, 0)))
        return _transaction_at(block, as_quantity(param(params, 1), "index", 64))

    def transaction_by_hash_and_index(self, params: list[Any]) -> Any:
        block = self._block_by_hash_param(param(params, 0))
        return _transaction_at(block, as_quantity(param(params, 1), "index", 64))

    def fee_history(self, params: list[Any]) -> Any:
        """geth's ``eth_feeHistory``: base fees (one more, the next block's), gas used
        ratios, the blob fields, and the tips actually paid at the requested percentiles of
        each block's gas (weighted by the gas each transaction used)."""
        count = min(max(as_count(param(params, 0), "block count"), 1), MAX_FEE_HISTORY_BLOCKS)
        newest = self.chain.header_at(self.number_tag(param(params, 1, "latest"))).block_number
        percentiles = _percentiles(param(params, 2, None))
        oldest = max(newest - count + 1, 0)
        headers = [self.chain.header_at(n) for n in range(oldest, newest + 1)]
        next_header = self.chain.next_header(headers[-1])
        body: dict[str, Any] = {
            "oldestBlock": encoding.quantity(oldest),
            "baseFeePerGas": [encoding.quantity(encoding.base_fee(h)) for h in headers]
            + [encoding.quantity(encoding.base_fee(next_header))],
            "gasUsedRatio": [h.gas_used / h.gas_limit for h in headers],
            "baseFeePerBlobGas": [
                encoding.quantity(fees.blob_base_fee(h)) for h in [*headers, next_header]
            ],
            "blobGasUsedRatio": [fees.blob_gas_used_ratio(h) for h in headers],
        }
        if percentiles is not None:
            rewards = []
            for header in headers:
                block = self.chain.block_by_number(header.block_number)
                assert block is not None
                paid = fees.tips_paid(block, self.chain.receipts(block))
                rewards.append([encoding.quantity(tip) for tip in fees.rewards(paid, percentiles)])
            body["reward"] = rewards
        return body

    # ----- accounts -----

    def balance(self, params: list[Any]) -> Any:
        address = as_address(param(params, 0))
        return encoding.quantity(self.chain.balance(address, self.tag(param(params, 1, "latest"))))

    def transaction_count(self, params: list[Any]) -> Any:
        address = as_address(param(params, 0))
        return encoding.quantity(self.chain.nonce(address, self.tag(param(params, 1, "latest"))))

    def code(self, params: list[Any]) -> Any:
        address = as_address(param(params, 0))
        return encoding.data(self.chain.code(address, self.tag(param(params, 1, "latest"))))

    def storage_at(self, params: list[Any]) -> Any:
        address = as_address(param(params, 0))
        slot = as_slot(param(params, 1))
        value = self.chain.storage_at(address, slot, self.tag(param(params, 2, "latest")))
        return encoding.data(value.to_bytes(32, "big"))

    # ----- execution -----

    def call_request(self, value: Any) -> CallRequest:
        if not isinstance(value, dict):
            raise InvalidParams("invalid call object: expected an object")
        data = call_data(value)
        if value.get("gasPrice") is not None and (
            value.get("maxFeePerGas") is not None or value.get("maxPriorityFeePerGas") is not None
        ):
            raise InvalidParams(
                "both gasPrice and (maxFeePerGas or maxPriorityFeePerGas) specified"
            )
        request = CallRequest(
            sender=as_address(value["from"]) if value.get("from") is not None else b"\x00" * 20,
            to=as_address(value["to"]) if value.get("to") is not None else b"",
            data=as_bytes(data, "call data"),
            value=as_quantity(value.get("value") or "0x0", "value"),
            gas=as_quantity(value["gas"], "gas", 64) if value.get("gas") else None,
            gas_price=_optional_quantity(value, "gasPrice"),
            max_fee_per_gas=_optional_quantity(value, "maxFeePerGas"),
            max_priority_fee_per_gas=_optional_quantity(value, "maxPriorityFeePerGas"),
        )
        cap, tip = request.max_fee_per_gas, request.max_priority_fee_per_gas
        if cap is not None and tip is not None and tip > cap:
            # anvil's words; geth refuses it too (-32000 "maxFeePerGas (1) < maxPriorityFeePerGas
            # (2)"); a call priced so was run as if its tip were the cap
            raise InvalidParams(
                "Invalid input: `max_priority_fee_per_gas` greater than `max_fee_per_gas`"
            )
        return request

    def call(self, params: list[Any]) -> Any:
        request = self.call_request(param(params, 0))
        return encoding.data(self.chain.call(request, self.tag(param(params, 1, "latest"))))

    def estimate_gas(self, params: list[Any]) -> Any:
        request = self.call_request(param(params, 0))
        gas = self.chain.estimate_gas(request, self.tag(param(params, 1, "latest")))
        return encoding.quantity(gas)

    def create_access_list(self, params: list[Any]) -> Any:
        request = self.call_request(param(params, 0))
        found = self.chain.create_access_list(request, self.tag(param(params, 1, "latest")))
        return {
            "accessList": [
                {
                    "address": encoding.address(address),
                    "storageKeys": [encoding.data(slot.to_bytes(32, "big")) for slot in slots],
                }
                for address, slots in found.entries
            ],
            "gasUsed": encoding.quantity(found.gas_used),
        }

    def send_raw_transaction(self, params: list[Any]) -> Any:
        raw = as_bytes(param(params, 0), "raw transaction")
        return encoding.data(self.chain.send_raw_transaction(raw).hash)

    # ----- logs and filters -----

    def log_criteria(self, query: Any) -> LogCriteria:
        """``eth_getLogs``/``eth_newFilter`` criteria, validated as nodes validate them."""
        if not isinstance(query, dict):
            raise InvalidParams("invalid filter: expected an object")
        addresses = query.get("address") or []
        if isinstance(addresses, str):
            addresses = [addresses]
        raw_topics = query.get("topics") or []
        if not isinstance(addresses, list) or not isinstance(raw_topics, list):
            raise InvalidParams("invalid filter: address and topics must be arrays")
        if len(raw_topics) > MAX_TOPICS:
            raise InvalidParams("exceeded maximum topics len")
        topics: list[tuple[bytes, ...] | None] = []
        for position in raw_topics:
            if position is None:
                topics.append(None)
                continue
            options = position if isinstance(position, list) else [position]
            if len(options) > MAX_OPTIONS:
                raise InvalidParams(f"too many topics at one position: at most {MAX_OPTIONS}")
            topics.append(tuple(as_bytes(t, "topic", 32) for t in options if t is not None))
        if len(addresses) > MAX_OPTIONS:
            raise InvalidParams(f"too many addresses: at most {MAX_OPTIONS}")
        criteria = LogCriteria(
            from_block=self.number_tag(_latest_when_unset(query.get("fromBlock"))),
            to_block=self.number_tag(_latest_when_unset(query.get("toBlock"))),
            addresses=tuple(as_address(a) for a in addresses),
            topics=tuple(t if t else None for t in topics),
        )
        if query.get("blockHash") is None:
            return criteria
        if query.get("fromBlock") is not None or query.get("toBlock") is not None:
            raise InvalidParams(
                "cannot specify both blockHash and fromBlock/toBlock, choose one or the other"
            )
        block_hash = as_bytes(query["blockHash"], "block hash", 32)
        block = self.chain.block_by_hash(block_hash)
        if block is None:
            raise ChainError("unknown block")
        return replace(criteria, block_hash=block_hash, block_number=int(block.number))

    def logs(self, params: list[Any]) -> Any:
        criteria = self.log_criteria(param(params, 0))
        found = self.index.logs(criteria.resolve(self.chain.head().block_number))
        return [entry.to_rpc() for entry in found]

    def new_filter(self, params: list[Any]) -> Any:
        criteria = self.log_criteria(param(params, 0))
        head = self.chain.head().block_number
        criteria.resolve(head)  # refused now, as eth_getLogs would be, not at the first poll
        return self.filters.install(criteria, head, client_var.get())

    def new_block_filter(self, params: list[Any]) -> Any:
        return self.filters.install(None, self.chain.head().block_number, client_var.get())

    def filter_changes(self, params: list[Any]) -> Any:
        filter_id = _filter_id(param(params, 0))
        changes = self.filters.changes(filter_id, self.chain.head().block_number)
        reported = changes.last
        if changes.criteria is None:
            hashes = self.chain.canonical_hashes(changes.first, changes.last)
            answer: list[Any] = [encoding.data(block_hash) for block_hash in hashes]
        else:
            reported = self._indexed_through(changes.last)
            window = changes.criteria.window(changes.first, reported)
            found, covered = self.index.logs_page(window) if window else ([], reported)
            if window is not None and covered < window.to_block:
                reported = covered  # the rest comes with the next poll
            answer = [entry.to_rpc() for entry in found]
        self.filters.reported(filter_id, reported)
        return answer

    def _indexed_through(self, head: int) -> int:
        """The last block up to ``head`` the event index holds. A log filter reports no
        further: a block mined but not indexed yet (the index catches up after a failed
        write) would otherwise be passed over, and its events never reported."""
        cursor = self.index.cursor()
        return -1 if cursor is None else min(head, cursor[0])

    def filter_logs(self, params: list[Any]) -> Any:
        criteria = self.filters.criteria(_filter_id(param(params, 0)))
        found = self.index.logs(criteria.resolve(self.chain.head().block_number))
        return [entry.to_rpc() for entry in found]

    def uninstall_filter(self, params: list[Any]) -> Any:
        return self.filters.uninstall(_filter_id(param(params, 0)))


def _filter_id(value: Any) -> str:
    if not isinstance(value, str) or not value.startswith("0x") or len(value) > 66:
        raise InvalidParams(f"invalid filter id: {value!r}")
    return value.lower()
