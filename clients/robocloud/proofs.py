"""Record ids and record proofs: what a robot checks with hashlib and two JSON-RPC calls.

A proof (``GET /v1/records/{id}/proof`` of a storage node) chains four facts, each checked
here without trusting the node:

1. the record's canonical (JCS) bytes are leaf ``leaf_index`` of its template's RFC 6962 log
   of ``tree_size`` leaves with root ``template_root`` (an inclusion proof);
2. that head, the JCS bytes of ``{"template", "size", "root"}``, is leaf ``tmt_leaf_index`` of
   the epoch's Template Merkle Tree with root ``tmt_root`` (a second inclusion proof);
3. ``AnchorLog.anchorAt(node, epoch)`` on the chain answers ``tmt_root`` anchored in block
   ``anchor.block`` (one ``eth_call``);
4. ``anchor.tx`` is the transaction that anchored it: its receipt (``eth_getTransactionReceipt``)
   succeeded in that block and holds AnchorLog's ``Anchored(node, epoch, tmt_root, ...)`` log.

The call is encoded and the answers decoded by hand (selectors, topics and 32-byte words) so
that verification needs no ABI library, only SHA-256 and JSON-RPC: this module imports nothing
of ``robocloud.ledger``, which brings eth-abi, eth-account and httpx with it. The AnchorLog
address must come from somewhere the robot trusts (its configuration, or the ledger's
``/v1/contracts``), never from the proof itself.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from robocloud import jcs, merkle
from robocloud.errors import FormatError, InvalidAnswerError
from robocloud.templates import canonical_record

ANCHOR_AT_SELECTOR = bytes.fromhex("d658cc42")
"""keccak-256("anchorAt(address,uint64)")[:4], checked against AnchorLog's ABI in the tests."""
ANCHORED_TOPIC = bytes.fromhex("a6a1e5d9c6386797ea92527642b4573f6b32e51a5e5407b15f976bc5657adad1")
"""keccak-256("Anchored(address,uint64,bytes32,uint64,uint64)"), the event's first topic,
checked against AnchorLog's ABI in the tests."""

RECORD_ID = re.compile(r"([a-z][a-z0-9_]{0,62})-([1-9][0-9]{0,8})-(0|[1-9][0-9]{0,17})")
MAX_PROOF_NODES = 64
"""A tree of 2**64 leaves needs 64 siblings: a longer list is not a proof."""

_HASH_HEX = re.compile(r"[0-9a-f]{64}")
_ADDRESS = re.compile(r"0x[0-9a-fA-F]{40}")
_BYTES32 = re.compile(r"0x[0-9a-fA-F]{64}")
_QUANTITY = re.compile(r"0x(?:0|[1-9a-fA-F][0-9a-fA-F]{0,15})")
"""A JSON-RPC quantity below 2**64, with no leading zeros (as the spec writes one)."""
_DATA = re.compile(r"0x(?:[0-9a-fA-F]{2})*")
_ANCHOR_AT_ANSWER = re.compile(r"0x[0-9a-fA-F]{256}")
MAX_TOPICS = 4

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
                tx=_text(anchor, "tx", _BYTES32, "anchor."),
                block=_count(anchor, "block", "anchor."),
            ),
        )

    def to_json(self) -> dict[str, Any]:
        """The proof document again, made only of the fields parsed: once verified, a
        consumer can trust every key (the anchor's tx and block too, both checked against
        the chain), where the node's whole answer may carry others."""
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


def anchor_at_call(contract: str, node: str, epoch: int) -> dict[str, str]:
    """The ``eth_call`` object of ``AnchorLog.anchorAt(node, epoch)``."""
    data = ANCHOR_AT_SELECTOR + _address_word(node) + epoch.to_bytes(32, "big")
    return {"to": contract, "data": "0x" + data.hex()}


@dataclass(frozen=True)
class ChainAnchor:
    """What ``AnchorLog.anchorAt`` answers: all zero when the node anchored nothing."""

    root: bytes
    record_count: int
    timestamp: int
    block: int


def anchor_at(rpc: EthCall, contract: str, node: str, epoch: int) -> ChainAnchor:
    """What the chain says ``node`` anchored for ``epoch``, decoded strictly: exactly four
    words, the last three uint64 (a longer or dirtier answer is not the contract's)."""
    result = rpc("eth_call", [anchor_at_call(contract, node, epoch), "latest"])
    if not isinstance(result, str) or not _ANCHOR_AT_ANSWER.fullmatch(result):
        raise ProofVerificationError(
            f"AnchorLog.anchorAt answered {result!r:.100}, not four 32-byte words"
        )
    words = [bytes.fromhex(result[2 + 64 * i : 66 + 64 * i]) for i in range(4)]
    if any(word[:24] != bytes(24) for word in words[1:]):
        raise ProofVerificationError(
            f"AnchorLog.anchorAt answered {result!r:.100}, a count, time or block past uint64"
        )
    count, timestamp, block = (int.from_bytes(word, "big") for word in words[1:])
    return ChainAnchor(words[0], count, timestamp, block)


def check_anchor_at(rpc: EthCall, proof: RecordProof, anchor_log: str) -> None:
    """Step 3: AnchorLog holds the proof's TMT root for its node and epoch, anchored in the
    proof's block (else ``anchor.block`` would be only the node's word)."""
    node, epoch = proof.anchor.node, proof.epoch
    on_chain = anchor_at(rpc, anchor_log, node, epoch)
    if on_chain.root != proof.tmt_root:
        raise ProofVerificationError(
            f"AnchorLog holds {on_chain.root.hex()} for epoch {epoch} of {node}, "
            f"the proof's TMT root is {proof.tmt_root.hex()}"
        )
    if on_chain.block != proof.anchor.block:
        raise ProofVerificationError(
            f"AnchorLog anchored epoch {epoch} of {node} in block {on_chain.block}, "
            f"the proof says block {proof.anchor.block}"
        )


@dataclass(frozen=True)
class Log:
    """A receipt's log, as the checks below read it."""

    address: str
    topics: list[bytes]
    data: bytes


@dataclass(frozen=True)
class TxReceipt:
    """The parts of a transaction receipt that vouch for an anchor.

    ``robocloud.ledger.transactions.Receipt`` parses receipts for the robot's own
    transactions, but importing it would load the ledger package (eth-abi, eth-account,
    httpx) into a verifier that needs only JSON-RPC; this one is stricter on quantities too.
    """

    tx: str
    block: int
    status: int
    logs: list[Log]

    @classmethod
    def from_rpc(cls, raw: Any, tx: str) -> TxReceipt:
        """The chain's receipt for ``tx``; a malformed one is a ``ProofVerificationError``
        naming the field."""
        where = f"the receipt of {tx}"
        if not isinstance(raw, Mapping):
            raise ProofVerificationError(f"{where} is not a JSON object: {raw!r:.100}")
        logs = raw.get("logs")
        if not isinstance(logs, list):
            raise ProofVerificationError(f"{where}: logs is not a list: {logs!r:.100}")
        return cls(
            tx=_rpc_text(raw.get("transactionHash"), _BYTES32, f"{where}: transactionHash"),
            block=int(_rpc_text(raw.get("blockNumber"), _QUANTITY, f"{where}: blockNumber"), 16),
            status=int(_rpc_text(raw.get("status"), _QUANTITY, f"{where}: status"), 16),
            logs=[_log(item, f"{where}: logs[{i}]") for i, item in enumerate(logs)],
        )


def _rpc_text(value: Any, pattern: re.Pattern[str], what: str) -> str:
    if not isinstance(value, str) or not pattern.fullmatch(value):
        raise ProofVerificationError(f"{what} is malformed: {value!r:.100}")
    return value


def _log(raw: Any, where: str) -> Log:
    if not isinstance(raw, Mapping):
        raise ProofVerificationError(f"{where} is not a JSON object: {raw!r:.100}")
    topics = raw.get("topics")
    if not isinstance(topics, list) or len(topics) > MAX_TOPICS:
        raise ProofVerificationError(f"{where}: topics is not a list of at most {MAX_TOPICS}")
    return Log(
        address=_rpc_text(raw.get("address"), _ADDRESS, f"{where}: address"),
        topics=[
            bytes.fromhex(_rpc_text(topic, _BYTES32, f"{where}: topics[{i}]")[2:])
            for i, topic in enumerate(topics)
        ],
        data=bytes.fromhex(_rpc_text(raw.get("data"), _DATA, f"{where}: data")[2:]),
    )


def check_anchor_tx(rpc: EthCall, proof: RecordProof, anchor_log: str) -> None:
    """Step 4: ``anchor.tx`` is the transaction that anchored the proof's root (one
    ``eth_getTransactionReceipt``), so a consumer of a verified proof can follow it."""
    tx = proof.anchor.tx
    raw = rpc("eth_getTransactionReceipt", [tx])
    if raw is None:
        raise ProofVerificationError(f"the chain has no receipt for the anchor's tx {tx}")
    receipt = TxReceipt.from_rpc(raw, tx)
    if receipt.tx.lower() != tx.lower():
        raise ProofVerificationError(f"asked for the receipt of {tx}, got that of {receipt.tx}")
    if receipt.status != 1:
        raise ProofVerificationError(f"the anchor's tx {tx} failed (status {receipt.status})")
    if receipt.block != proof.anchor.block:
        raise ProofVerificationError(
            f"the anchor's tx {tx} is in block {receipt.block}, "
            f"the proof says block {proof.anchor.block}"
        )
    _check_anchored_log(receipt.logs, proof, anchor_log)


def _check_anchored_log(logs: list[Log], proof: RecordProof, anchor_log: str) -> None:
    """One of ``logs`` is AnchorLog's ``Anchored`` event of the proof's node, epoch and root."""
    tx = proof.anchor.tx
    events = [
        log
        for log in logs
        if log.address.lower() == anchor_log.lower() and log.topics[:1] == [ANCHORED_TOPIC]
    ]
    if not events:
        raise ProofVerificationError(f"the anchor's tx {tx} has no Anchored log of {anchor_log}")
    wanted = [ANCHORED_TOPIC, _address_word(proof.anchor.node), proof.epoch.to_bytes(32, "big")]
    ours = [log for log in events if log.topics == wanted]
    if not ours:
        raise ProofVerificationError(
            f"the anchor's tx {tx} anchored {_anchored_what(events[0])}, "
            f"not epoch {proof.epoch} of {proof.anchor.node}"
        )
    if not any(log.data[:32] == proof.tmt_root for log in ours):
        raise ProofVerificationError(
            f"the anchor's tx {tx} anchored root {ours[0].data[:32].hex()}, "
            f"the proof's TMT root is {proof.tmt_root.hex()}"
        )


def _anchored_what(log: Log) -> str:
    """An ``Anchored`` log's node and epoch, for a message (its topics, when not three)."""
    if len(log.topics) != 3:
        return f"topics {[topic.hex() for topic in log.topics]}"
    return f"epoch {int.from_bytes(log.topics[2], 'big')} of 0x{log.topics[1][12:].hex()}"


def _address_word(address: str) -> bytes:
    """A ``0x`` address as an ABI word (and an indexed topic): 12 zero bytes, then it."""
    return bytes.fromhex(address[2:]).rjust(32, b"\0")


def rpc_chain_id(rpc: EthCall) -> int:
    """The chain ``rpc`` reads (``eth_chainId``): the anchor it confirms is on that chain,
    whatever chain id the proof claims."""
    result = rpc("eth_chainId", [])
    if not isinstance(result, str) or not re.fullmatch(r"0x[0-9a-fA-F]{1,64}", result):
        raise InvalidAnswerError(
            f"the node sent {result!r:.80} where eth_chainId's quantity belongs"
        )
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
    anchor's. Two JSON-RPC calls reach ``rpc``: ``eth_call`` of ``AnchorLog.anchorAt`` and
    ``eth_getTransactionReceipt`` of ``anchor.tx``. Raises :class:`ProofFormatError` for a
    malformed document and :class:`ProofVerificationError` for one that does not hold (or a
    chain answer that is malformed).
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
    check_anchor_at(rpc, proof, anchor_log)
    check_anchor_tx(rpc, proof, anchor_log)
    return proof
