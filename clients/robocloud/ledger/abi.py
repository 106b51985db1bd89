"""Calls, results, events and revert data of robocloud's contracts, from their committed ABIs.

The ABIs ship inside the SDK (``robocloud/abi/*.json``, written by ``contracts/compile.mjs``)
so that a robot needs neither the repository nor a compiler, and so that everything it sends
and reads is encoded and decoded by ``eth-abi`` against exactly what was deployed.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from importlib.resources import files
from typing import Any

from eth_abi.abi import decode, encode
from eth_abi.exceptions import DecodingError
from eth_utils.address import to_checksum_address
from eth_utils.crypto import keccak

ERROR_SELECTOR = keccak(text="Error(string)")[:4]
PANIC_SELECTOR = keccak(text="Panic(uint256)")[:4]

PANIC_CODES = {
    0x01: "assertion failed",
    0x11: "arithmetic overflow or underflow",
    0x12: "division or modulo by zero",
    0x21: "invalid enum value",
    0x22: "invalid storage byte array",
    0x31: "pop on an empty array",
    0x32: "array index out of bounds",
    0x41: "out of memory",
    0x51: "call to an uninitialised function",
}


def abi_type(param: dict[str, Any]) -> str:
    """The canonical type of an ABI parameter; tuples are spelled out from their components."""
    kind = str(param["type"])
    if not kind.startswith("tuple"):
        return kind
    inner = ",".join(abi_type(component) for component in param["components"])
    return f"({inner}){kind.removeprefix('tuple')}"


def signature(entry: dict[str, Any]) -> str:
    return f"{entry['name']}({','.join(abi_type(p) for p in entry['inputs'])})"


def _normalise(kind: str, value: Any) -> Any:
    """Addresses as checksummed strings, so results compare equal to ``Identity.address``."""
    if kind == "address":
        return to_checksum_address(value)
    return value


@dataclass(frozen=True)
class DecodedLog:
    """One log of a known event, with its arguments by name and where it was emitted."""

    event: str
    args: dict[str, Any]
    address: str
    block_number: int
    tx_hash: str
    log_index: int


class ContractAbi:
    """One contract's functions, events and custom errors, looked up by name or selector."""

    def __init__(self, name: str, abi: list[dict[str, Any]]) -> None:
        self.name = name
        self.abi = abi
        self.functions: dict[str, dict[str, Any]] = {}
        self.events: dict[str, dict[str, Any]] = {}
        self.errors: dict[bytes, dict[str, Any]] = {}
        self.topics: dict[bytes, dict[str, Any]] = {}
        for entry in abi:
            kind = entry.get("type")
            if kind == "function":
                if entry["name"] in self.functions:
                    raise ValueError(f"{name}.{entry['name']} is overloaded; call it by signature")
                self.functions[entry["name"]] = entry
            elif kind == "event":
                self.events[entry["name"]] = entry
                self.topics[keccak(text=signature(entry))] = entry
            elif kind == "error":
                self.errors[keccak(text=signature(entry))[:4]] = entry

    @classmethod
    def load(cls, name: str) -> ContractAbi:
        """The ABI of ``name`` as shipped in the SDK package."""
        resource = files("robocloud") / "abi" / f"{name}.json"
        try:
            artifact = json.loads(resource.read_text())
        except FileNotFoundError as exc:
            raise ValueError(f"the SDK ships no ABI for contract {name!r}") from exc
        return cls(name, list(artifact["abi"]))

    def _function(self, name: str) -> dict[str, Any]:
        try:
            return self.functions[name]
        except KeyError as exc:
            raise ValueError(f"{self.name} has no function {name!r}") from exc

    def encode_call(self, function: str, *args: Any) -> bytes:
        entry = self._function(function)
        types = [abi_type(p) for p in entry["inputs"]]
        if len(args) != len(types):
            raise TypeError(f"{self.name}.{function} takes {len(types)} arguments, not {len(args)}")
        return keccak(text=signature(entry))[:4] + encode(types, list(args))

    def encode_constructor(self, *args: Any) -> bytes:
        inputs: list[dict[str, Any]] = next(
            (e["inputs"] for e in self.abi if e.get("type") == "constructor"), []
        )
        return encode([abi_type(p) for p in inputs], list(args))

    def decode_output(self, function: str, data: bytes) -> tuple[Any, ...]:
        outputs = self._function(function)["outputs"]
        types = [abi_type(p) for p in outputs]
        values = decode(types, data)
        return tuple(_normalise(kind, value) for kind, value in zip(types, values, strict=True))

    def event_topic(self, event: str) -> bytes:
        return keccak(text=signature(self.events[event]))

    def decode_log(self, log: dict[str, Any]) -> DecodedLog | None:
        """Decode a JSON-RPC log object, or None when it is not one of this contract's events.

        Indexed arguments of dynamic types (``bytes``, ``string``) are only their keccak hash
        in a topic, so they come back as those 32 bytes.
        """
        topics = [bytes.fromhex(str(t).removeprefix("0x")) for t in log.get("topics", [])]
        entry = self.topics.get(topics[0]) if topics else None
        if entry is None:
            return None
        indexed = [p for p in entry["inputs"] if p["indexed"]]
        plain = [p for p in entry["inputs"] if not p["indexed"]]
        args: dict[str, Any] = {}
        for param, topic in zip(indexed, topics[1:], strict=True):
            kind = abi_type(param)
            dynamic = kind in {"bytes", "string"} or kind.endswith("]") or kind.startswith("(")
            args[param["name"]] = topic if dynamic else _normalise(kind, decode([kind], topic)[0])
        data = bytes.fromhex(str(log.get("data", "0x")).removeprefix("0x"))
        values = decode([abi_type(p) for p in plain], data)
        for param, value in zip(plain, values, strict=True):
            args[param["name"]] = _normalise(abi_type(param), value)
        return DecodedLog(
            event=str(entry["name"]),
            args=args,
            address=to_checksum_address(str(log["address"])),
            block_number=check_block(uint64_quantity(log["blockNumber"])),
            tx_hash=check_hash(log["transactionHash"]),
            log_index=uint64_quantity(log["logIndex"]),
        )

    def decode_error(self, data: bytes) -> str | None:
        """A custom error of this contract as ``Name(arg, ...)``, or None if it is not one."""
        entry = self.errors.get(data[:4])
        if entry is None:
            return None
        values = decode([abi_type(p) for p in entry["inputs"]], data[4:])
        return f"{entry['name']}({', '.join(repr(v) for v in values)})"


_QUANTITY = re.compile(r"0x(?:0|[1-9a-fA-F][0-9a-fA-F]{0,15})")


def uint64_quantity(value: Any) -> int:
    """A log's block number or index: a JSON-RPC quantity (``0x``, no leading zeros) within
    uint64; a ``ValueError`` for anything else. ``int(x, 16)`` took ``"-5"`` and numbers of
    any size, which a storage node then published as its anchor's, and which wedged the
    ledger's external-node index (it parses a node's logs with this too)."""
    if not isinstance(value, str) or not _QUANTITY.fullmatch(value):
        raise ValueError(f"{str(value)[:40]!r} is not a uint64 quantity")
    return int(value, 16)


MAX_BLOCK_NUMBER = 2**63 - 1
"""The last block number taken from a node, though blocks are uint64 on chain: geth reads a
block number as an int64 (``rpc.BlockNumber``), so no later block can be asked for, and it
is SQLite's largest integer. A receipt, log or ``anchorAt`` of block 2^63 was taken, and the
storage node's anchorer, having sent its anchor, raised OverflowError recording it."""


def check_block(number: int) -> int:
    """``number``, a block number a node sent; a ``ValueError`` past ``MAX_BLOCK_NUMBER``."""
    if number > MAX_BLOCK_NUMBER:
        raise ValueError(f"block {number}, past 2^63 - 1, the last block a node can name")
    return number


_HASH = re.compile(r"0x[0-9a-fA-F]{64}")


def check_hash(value: Any) -> str:
    """A 32-byte hash a node sent (a transaction's, a block's) as lower-case ``0x``-hex, the
    way ``transaction_hash`` writes one; a ``ValueError`` for anything else. ``str()`` of the
    node's word was taken: a storage node recovering from a crash recorded and published as
    its anchor's transaction whatever text the log held."""
    if not isinstance(value, str) or not _HASH.fullmatch(value):
        raise ValueError(f"{str(value)[:80]!r} is not a 32-byte hash (0x and 64 hex digits)")
    return value.lower()


def decode_revert(data: bytes, contracts: list[ContractAbi] | None = None) -> str:
    """A readable reason for revert data: ``Error(string)``, ``Panic(uint256)`` or a custom
    error of one of ``contracts``; the raw hex when none of them fits."""
    if not data:
        return "execution reverted without a reason"
    try:
        if data[:4] == ERROR_SELECTOR:
            return str(decode(["string"], data[4:])[0])
        if data[:4] == PANIC_SELECTOR:
            code = int(decode(["uint256"], data[4:])[0])
            return f"panic 0x{code:02x}: {PANIC_CODES.get(code, 'unknown panic code')}"
        for contract in contracts or []:
            custom = contract.decode_error(data)
            if custom is not None:
                return custom
    except (DecodingError, UnicodeDecodeError, OverflowError):
        # What eth_abi's decoders raise on data: DecodingError (short data, bad padding or
        # pointer), UnicodeDecodeError (a string not UTF-8) and OverflowError (a length word
        # past 2^63, which a read cannot take); their ValueErrors are for malformed types only.
        pass
    return f"execution reverted with undecodable data {bounded_hex(data)}"


MAX_SHOWN_BYTES = 512
"""Bytes of revert data or an error message an exception's text shows: a node may send
megabytes, which a service would keep, log and serve."""


def bounded_hex(data: bytes) -> str:
    """``0x``-hex of ``data``, its first ``MAX_SHOWN_BYTES`` and its length when longer."""
    if len(data) <= MAX_SHOWN_BYTES:
        return "0x" + data.hex()
    return f"0x{data[:MAX_SHOWN_BYTES].hex()}... ({len(data)} bytes)"
