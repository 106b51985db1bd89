"""Record ids and record proofs: what a robot checks with hashlib and one ``eth_call``.

A proof (``GET /v1/records/{id}/proof`` of a storage node) chains three facts, each checked
here without trusting the node:

1. the record's canonical (JCS) bytes are leaf ``leaf_index`` of its template's RFC 6962 log
   of ``tree_size`` leaves with root ``template_root`` (an inclusion proof);
2. that head, the JCS bytes of ``{"template", "size", "root"}``, is leaf ``tmt_leaf_index`` of
   the epoch's Template Merkle Tree with root ``tmt_root`` (a second inclusion proof);
3. ``AnchorLog.rootAt(node, epoch)`` on the chain answers ``tmt_root`` (one ``eth_call``).

The call is encoded by hand (selector and two words) so that verification needs no ABI
library, only SHA-256 and JSON-RPC. The AnchorLog address must come from somewhere the robot
trusts (its configuration, or the ledger's ``/v1/contracts``), never from the proof itself.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from robocloud import jcs, merkle
from robocloud.errors import FormatError, InvalidAnswerError
from robocloud.templates import canonical_record

ROOT_AT_SELECTOR = bytes.fromhex("899314ce")
"""keccak-256("rootAt(address,uint64)")[:4], checked against AnchorLog's ABI in the tests."""

RECORD_ID = re.compile(r"([a-z][a-z0-9_]{0,62})-([1-9][0-9]{0,8})-(0|[1-9][0-9]{0,17})")
MAX_PROOF_NODES = 64
"""A tree of 2**64 leaves needs 64 siblings: a longer list is not a proof."""

_HASH_HEX = re.compile(r"[0-9a-f]{64}")
_ADDRESS = re.compile(r"0x[0-9a-fA-F]{40}")
_TX = re.compile(r"0x[0-9a-fA-F]{64}")

EthCall = Callable[[str, list[Any]], Any]
"""A JSON-RPC request function: ``(method, params) -> result`` (``JsonRpcClient.request``)."""


class RecordIdError(FormatError):
    """Text that is not a record id ``<name>-<version>-<index>``."""

    def __init__(self, text: str) -> None:
        super().__init__(f"{text[:100]!r} is not a record id (<name>-<version>-<index>)")
        self.text = text


class ProofFormatError(FormatError):
    """A proof document whose fields are missing or of the wrong shape; ``field`` names it."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"proof field {field}: {message}")
        self.field = field


class ProofVerificationError(InvalidAnswerError):
    """A well-formed proof that does not hold: the record is not what the chain commits to."""


@dataclass(frozen=True, order=True)
class RecordId:
    name: str
    version: int
    index: int

    @classmethod
    def parse(cls, text: str) -> RecordId:
        match = RECORD_ID.fullmatch(text)
        if match is None:
            raise RecordIdError(text)
        return cls(match[1], int(match[2]), int(match[3]))

    @property
    def template(self) -> str:
        return f"{self.name}@{self.version}"

    def __str__(self) -> str:
        return f"{self.name}-{self.version}-{self.index}"


@dataclass(frozen=True)
class AnchorRef:
    chain_id: int
    contract: str
    node: str
    epoch: int
    tx: str
    block: int

    def describe(self) -> dict[str, Any]:
        return {
            "chain_id": self.chain_id,
            "contract": self.contract,
            "node": self.node,
            "epoch": self.epoch,
            "tx": self.tx,
            "block": self.block,
        }


@dataclass(frozen=True)
class RecordProof:
    """A parsed proof document: every field typed, nothing yet verified."""

    record: Any
    leaf_index: int
    tree_size: int
    template_root: bytes
    inclusion: list[bytes]
    epoch: int
    tmt_leaf_index: int
    tmt_size: int
    tmt_inclusion: list[bytes]
    tmt_root: bytes
    anchor: AnchorRef

    @classmethod
    def from_json(cls, body: Any) -> RecordProof:
        if not isinstance(body, Mapping):
            raise ProofFormatError("(document)", "not a JSON object")
        anchor = body.get("anchor")
        if not isinstance(anchor, Mapping):
            raise ProofFormatError("anchor", "not a JSON object")
        record = body.get("record")
        if not isinstance(record, Mapping) or not isinstance(record.get("template"), str):
            raise ProofFormatError("record", "not a record object with a template")
        return cls(
            record=record,
            leaf_index=_count(body, "leaf_index"),
            tree_size=_count(body, "tree_size"),
            template_root=_hash(body, "template_root"),
            inclusion=_hashes(body, "inclusion"),
            epoch=_count(body, "epoch"),
            tmt_leaf_index=_count(body, "tmt_leaf_index"),
            tmt_size=_count(body, "tmt_size"),
            tmt_inclusion=_hashes(body, "tmt_inclusion"),
            tmt_root=_hash(body, "tmt_root"),
            anchor=AnchorRef(
                chain_id=_count(anchor, "chain_id", "anchor."),
                contract=_text(anchor, "contract", _ADDRESS, "anchor."),
                node=_text(anchor, "node", _ADDRESS, "anchor."),
                epoch=_count(anchor, "epoch", "anchor."),
                tx=_text(anchor, "tx", _TX, "anchor."),
                block=_count(anchor, "block", "anchor."),
            ),
        )

    def to_json(self) -> dict[str, Any]:
        """The proof document again, made only of the fields parsed: once verified, a
        consumer can trust every key, where the node's whole answer may carry others."""
        return {
            "record": self.record,
            "leaf_index": self.leaf_index,
            "tree_size": self.tree_size,
            "template_root": self.template_root.hex(),
            "inclusion": [node.hex() for node in self.inclusion],
            "epoch": self.epoch,
            "tmt_leaf_index": self.tmt_leaf_index,
            "tmt_size": self.tmt_size,
            "tmt_inclusion": [node.hex() for node in self.tmt_inclusion],
            "tmt_root": self.tmt_root.hex(),
            "anchor": self.anchor.describe(),
        }

    @property
    def template(self) -> str:
        return str(self.record["template"])

    def check_hashes(self) -> None:
        """Steps 1 and 2: the record is in its template log, that head in the epoch's TMT."""
        leaf = merkle.leaf_hash(canonical_record(self.record))
        try:
            merkle.verify_inclusion(
                self.leaf_index, self.tree_size, leaf, self.inclusion, self.template_root
            )
        except merkle.ProofError as exc:
            raise ProofVerificationError(f"the record is not in its template log: {exc}") from exc
        head = jcs.canonical(
            {"template": self.template, "size": self.tree_size, "root": self.template_root.hex()}
        )
        try:
            merkle.verify_inclusion(
                self.tmt_leaf_index,
                self.tmt_size,
                merkle.leaf_hash(head),
                self.tmt_inclusion,
                self.tmt_root,
            )
        except merkle.ProofError as exc:
            raise ProofVerificationError(f"the template head is not in the TMT: {exc}") from exc


def _field(body: Mapping[str, Any], name: str, prefix: str) -> Any:
    if name not in body:
        raise ProofFormatError(prefix + name, "missing")
    return body[name]


def _count(body: Mapping[str, Any], name: str, prefix: str = "") -> int:
    value = _field(body, name, prefix)
    if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < 2**64:
        raise ProofFormatError(prefix + name, f"not an integer in [0, 2**64): {value!r:.100}")
    return value


def _text(body: Mapping[str, Any], name: str, pattern: re.Pattern[str], prefix: str = "") -> str:
    value = _field(body, name, prefix)
    if not isinstance(value, str) or not pattern.fullmatch(value):
        raise ProofFormatError(prefix + name, f"malformed: {value!r:.100}")
    return value


def _hash(body: Mapping[str, Any], name: str) -> bytes:
    return bytes.fromhex(_text(body, name, _HASH_HEX))


def _hashes(body: Mapping[str, Any], name: str) -> list[bytes]:
    value = _field(body, name, "")
    if not isinstance(value, list) or len(value) > MAX_PROOF_NODES:
        raise ProofFormatError(name, f"not a list of at most {MAX_PROOF_NODES} hashes")
    hashes: list[bytes] = []
    for position, item in enumerate(value):
        if not isinstance(item, str) or not _HASH_HEX.fullmatch(item):
            raise ProofFormatError(f"{name}[{position}]", f"not 64 lowercase hex: {item!r:.100}")
        hashes.append(bytes.fromhex(item))
    return hashes


def root_at_call(contract: str, node: str, epoch: int) -> dict[str, str]:
    """The ``eth_call`` object of ``AnchorLog.rootAt(node, epoch)``."""
    data = ROOT_AT_SELECTOR + bytes.fromhex(node[2:]).rjust(32, b"\0") + epoch.to_bytes(32, "big")
    return {"to": contract, "data": "0x" + data.hex()}


def anchored_root(rpc: EthCall, contract: str, node: str, epoch: int) -> bytes:
    """What the chain says ``node`` anchored for ``epoch`` (32 zero bytes: nothing)."""
    result = rpc("eth_call", [root_at_call(contract, node, epoch), "latest"])
    if not isinstance(result, str) or not re.fullmatch(r"0x[0-9a-fA-F]{64}", result):
        raise ProofVerificationError(f"AnchorLog.rootAt answered {result!r:.100}, not a bytes32")
    return bytes.fromhex(result[2:])


def rpc_chain_id(rpc: EthCall) -> int:
    """The chain ``rpc`` reads (``eth_chainId``): the anchor it confirms is on that chain,
    whatever chain id the proof claims."""
    result = rpc("eth_chainId", [])
    if not isinstance(result, str) or not re.fullmatch(r"0x[0-9a-fA-F]{1,64}", result):
        raise InvalidAnswerError(f"eth_chainId answered {result!r:.100}, not a quantity")
    return int(result, 16)


def verify_record_proof(
    body: Any,
    rpc: EthCall,
    *,
    anchor_log: str,
    record_id: str | None = None,
    chain_id: int | None = None,
    node: str | None = None,
) -> RecordProof:
    """Check a proof document against the chain; the parsed proof when it holds.

    ``anchor_log`` is the AnchorLog address the robot trusts; ``record_id`` the id it asked
    for (the proof must be of that record); ``chain_id`` and ``node``, when given, must be the
    anchor's. Raises :class:`ProofFormatError` for a malformed document and
    :class:`ProofVerificationError` for one that does not hold.
    """
    proof = RecordProof.from_json(body)
    if record_id is not None:
        wanted = RecordId.parse(record_id)
        if (wanted.template, wanted.index) != (proof.template, proof.leaf_index):
            raise ProofVerificationError(
                f"asked for {wanted}, the proof is of leaf {proof.leaf_index} of {proof.template}"
            )
    if proof.anchor.epoch != proof.epoch:
        raise ProofVerificationError(
            f"the proof is of epoch {proof.epoch}, its anchor of epoch {proof.anchor.epoch}"
        )
    if proof.anchor.contract.lower() != anchor_log.lower():
        raise ProofVerificationError(
            f"the proof names AnchorLog {proof.anchor.contract}, the trusted one is {anchor_log}"
        )
    if chain_id is not None and proof.anchor.chain_id != chain_id:
        raise ProofVerificationError(
            f"the proof is anchored on chain {proof.anchor.chain_id}, not {chain_id}"
        )
    if node is not None and proof.anchor.node.lower() != node.lower():
        raise ProofVerificationError(f"the proof is anchored by {proof.anchor.node}, not {node}")
    proof.check_hashes()
    on_chain = anchored_root(rpc, anchor_log, proof.anchor.node, proof.epoch)
    if on_chain != proof.tmt_root:
        raise ProofVerificationError(
            f"AnchorLog holds {on_chain.hex()} for epoch {proof.epoch} of {proof.anchor.node}, "
            f"the proof's TMT root is {proof.tmt_root.hex()}"
        )
    return proof
