"""Record ids and proof documents: parsing refuses every malformed field; hashes are checked."""

from __future__ import annotations

from typing import Any

import pytest
from eth_utils.crypto import keccak

from robocloud import jcs, merkle
from robocloud.ledger.abi import ContractAbi
from robocloud.proofs import (
    ANCHOR_AT_SELECTOR,
    ANCHORED_TOPIC,
    EthCall,
    ProofFormatError,
    ProofVerificationError,
    RecordId,
    RecordIdError,
    RecordProof,
    anchor_at,
    anchor_at_call,
    verify_record_proof,
)
from services.storage.tmt import EpochTree, TemplateHead

NODE = "0x" + "12" * 20
CONTRACT = "0x" + "34" * 20
TX = "0x" + "ab" * 32
BLOCK = 9


def test_the_selector_and_topic_are_anchorlogs() -> None:
    assert keccak(text="anchorAt(address,uint64)")[:4] == ANCHOR_AT_SELECTOR
    abi = ContractAbi.load("AnchorLog")
    assert (
        anchor_at_call(CONTRACT, NODE, 7)["data"]
        == "0x" + abi.encode_call("anchorAt", NODE, 7).hex()
    )
    assert abi.event_topic("Anchored") == ANCHORED_TOPIC


def test_an_anchor_at_answer_decodes_as_the_abi_does() -> None:
    answer = anchor_at_answer("cd" * 32, block=2**64 - 1)
    decoded = ContractAbi.load("AnchorLog").decode_output("anchorAt", bytes.fromhex(answer[2:]))
    found = anchor_at(lambda _method, _params: answer, CONTRACT, NODE, 4)
    assert (found.root, found.record_count, found.timestamp, found.block) == decoded


@pytest.mark.parametrize(
    ("text", "parsed"),
    [("imu-1-0", RecordId("imu", 1, 0)), ("nav_sat2-12-345", RecordId("nav_sat2", 12, 345))],
)
def test_record_ids_round_trip(text: str, parsed: RecordId) -> None:
    assert RecordId.parse(text) == parsed
    assert str(parsed) == text
    assert parsed.template == f"{parsed.name}@{parsed.version}"


@pytest.mark.parametrize(
    "text",
    [
        "",
        "imu",
        "imu-1",
        "imu-1-",
        "Imu-1-0",
        "imu-0-0",
        "imu-1-00",
        "imu-1-1-1",
        "imu-1-" + "9" * 19,
    ],
)
def test_malformed_record_ids_are_refused(text: str) -> None:
    with pytest.raises(RecordIdError) as refused:
        RecordId.parse(text)
    assert refused.value.text == text


def proof_document(records: int = 5, index: int = 3) -> dict[str, Any]:
    values = [{"template": "imu@1", "t": i, "data": {"x": i / 3}} for i in range(records)]
    tree = merkle.MerkleTree([merkle.leaf_hash(jcs.canonical(value)) for value in values])
    heads = [
        TemplateHead("imu@1", records, tree.root()),
        TemplateHead("gps@1", 2, b"\x07" * 32),
        TemplateHead("zeta@3", 9, b"\x08" * 32),
    ]
    epoch = EpochTree.build(4, heads)
    position, inclusion = epoch.inclusion("imu@1")
    return {
        "record": values[index],
        "leaf_index": index,
        "tree_size": records,
        "template_root": tree.root().hex(),
        "inclusion": [node.hex() for node in tree.inclusion_proof(index)],
        "epoch": 4,
        "tmt_leaf_index": position,
        "tmt_size": 3,
        "tmt_inclusion": [node.hex() for node in inclusion],
        "tmt_root": epoch.root.hex(),
        "anchor": {
            "chain_id": 1337,
            "contract": CONTRACT,
            "node": NODE,
            "epoch": 4,
            "tx": TX,
            "block": BLOCK,
        },
    }


def anchor_at_answer(root: str, block: int = BLOCK) -> str:
    """``AnchorLog.anchorAt``'s answer: ``root`` (hex), 5 records, a time, ``block``."""
    words = [bytes.fromhex(root), *(n.to_bytes(32, "big") for n in (5, 1_700_000_000, block))]
    return "0x" + b"".join(words).hex()


def anchored_log(
    root: str, *, node: str = NODE, epoch: int = 4, contract: str = CONTRACT
) -> dict[str, Any]:
    """The ``Anchored`` log AnchorLog emits for ``node``'s ``epoch`` (a receipt's form)."""
    return {
        "address": contract,
        "topics": [
            "0x" + ANCHORED_TOPIC.hex(),
            "0x" + "00" * 12 + node[2:],
            "0x" + epoch.to_bytes(32, "big").hex(),
        ],
        "data": "0x" + root + anchor_at_answer(root)[66:194],
        "blockNumber": hex(BLOCK),
        "transactionHash": TX,
        "logIndex": "0x0",
        "removed": False,
    }


def anchor_receipt(root: str) -> dict[str, Any]:
    """The receipt of the tx that anchored ``root`` in block ``BLOCK``, with a log before."""
    return {
        "transactionHash": TX,
        "blockNumber": hex(BLOCK),
        "blockHash": "0x" + "cc" * 32,
        "status": "0x1",
        "gasUsed": "0xb5c8",
        "contractAddress": None,
        "logs": [{**anchored_log(root), "topics": ["0x" + "99" * 32]}, anchored_log(root)],
    }


def scripted_chain(
    document: dict[str, Any], chain_id: int = 1337, **answers: Any
) -> tuple[EthCall, list[tuple[str, list[Any]]]]:
    """A JSON-RPC function of chain ``chain_id`` on which ``document``'s anchor holds (its
    root anchored by its tx in its block), but for ``answers`` (by method name), and the
    calls it got."""
    sound = {
        "eth_chainId": hex(chain_id),
        "eth_call": anchor_at_answer(document["tmt_root"]),
        "eth_getTransactionReceipt": anchor_receipt(document["tmt_root"]),
    }
    calls: list[tuple[str, list[Any]]] = []

    def request(method: str, params: list[Any]) -> Any:
        calls.append((method, params))
        return {**sound, **answers}[method]

    return request, calls


SOUND_CALLS = [
    ("eth_call", [anchor_at_call(CONTRACT, NODE, 4), "latest"]),
    ("eth_getTransactionReceipt", [TX]),
]
"""What verifying ``proof_document()`` asks the chain."""


def test_a_sound_proof_checks_and_a_changed_field_does_not() -> None:
    document = proof_document()
    RecordProof.from_json(document).check_hashes()
    changed_record = {**document, "record": {**document["record"], "t": 4}}
    with pytest.raises(ProofVerificationError, match="template log"):
        RecordProof.from_json(changed_record).check_hashes()
    changed_size = {**document, "tree_size": 6}
    with pytest.raises(ProofVerificationError):
        RecordProof.from_json(changed_size).check_hashes()
    changed_tmt = {**document, "tmt_root": "00" * 32}
    with pytest.raises(ProofVerificationError, match="TMT"):
        RecordProof.from_json(changed_tmt).check_hashes()


def test_the_chain_decides() -> None:
    document = proof_document()
    rpc, calls = scripted_chain(document)
    verified = verify_record_proof(document, rpc, anchor_log=CONTRACT, record_id="imu-1-3")
    assert verified.leaf_index == 3
    assert calls == SOUND_CALLS
    rpc, _ = scripted_chain(document, eth_call=anchor_at_answer("00" * 32, block=0))
    with pytest.raises(ProofVerificationError, match="AnchorLog holds 0000"):
        verify_record_proof(document, rpc, anchor_log=CONTRACT)
    with pytest.raises(ProofVerificationError, match="chain 1337, not 1"):
        verify_record_proof(document, rpc, anchor_log=CONTRACT, chain_id=1)


ROOT = proof_document()["tmt_root"]
OTHER_ROOT = "ee" * 32


def receipt_with(**changes: Any) -> dict[str, Any]:
    return {**anchor_receipt(ROOT), **changes}


@pytest.mark.parametrize(
    ("answers", "match"),
    [
        (
            {"eth_call": anchor_at_answer(ROOT, block=8)},
            f"in block 8, the proof says block {BLOCK}",
        ),
        ({"eth_call": "0x" + ROOT}, "anchorAt answered '0x.*', not four 32-byte words"),
        ({"eth_call": anchor_at_answer(ROOT) + "00" * 32}, "not four 32-byte words"),
        ({"eth_call": None}, "anchorAt answered None"),
        (
            {"eth_call": anchor_at_answer(ROOT)[:-64] + "01" + "00" * 31},
            "a count, time or block past uint64",
        ),
        ({"eth_getTransactionReceipt": None}, f"no receipt for the anchor's tx {TX}"),
        (
            {"eth_getTransactionReceipt": receipt_with(status="0x0")},
            rf"tx {TX} failed \(status 0\)",
        ),
        (
            {"eth_getTransactionReceipt": receipt_with(blockNumber="0xa")},
            f"tx {TX} is in block 10, the proof says block {BLOCK}",
        ),
        (
            {"eth_getTransactionReceipt": receipt_with(transactionHash="0x" + "cd" * 32)},
            f"asked for the receipt of {TX}, got that of 0x{'cd' * 32}",
        ),
        ({"eth_getTransactionReceipt": receipt_with(logs=[])}, "has no Anchored log of"),
        (
            {
                "eth_getTransactionReceipt": receipt_with(
                    logs=[anchored_log(ROOT, contract="0x" + "56" * 20)]
                )
            },
            f"has no Anchored log of {CONTRACT}",
        ),
        (
            {
                "eth_getTransactionReceipt": receipt_with(
                    logs=[anchored_log(ROOT, node="0x" + "78" * 20)]
                )
            },
            f"anchored epoch 4 of 0x{'78' * 20}, not epoch 4 of {NODE}",
        ),
        (
            {"eth_getTransactionReceipt": receipt_with(logs=[anchored_log(ROOT, epoch=3)])},
            f"anchored epoch 3 of {NODE}, not epoch 4 of {NODE}",
        ),
        (
            {"eth_getTransactionReceipt": receipt_with(logs=[anchored_log(OTHER_ROOT)])},
            f"anchored root {OTHER_ROOT}, the proof's TMT root is {ROOT}",
        ),
        (
            {"eth_getTransactionReceipt": receipt_with(blockNumber="0x09")},
            "blockNumber is malformed: '0x09'",
        ),
        ({"eth_getTransactionReceipt": receipt_with(status=1)}, "status is malformed: 1"),
        ({"eth_getTransactionReceipt": [anchor_receipt(ROOT)]}, "is not a JSON object"),
        (
            {"eth_getTransactionReceipt": receipt_with(logs=[{**anchored_log(ROOT), "data": 0}])},
            r"logs\[0\]: data is malformed: 0",
        ),
    ],
    ids=[
        "anchor-block-differs",
        "anchor-at-one-word",
        "anchor-at-five-words",
        "anchor-at-null",
        "anchor-at-block-past-uint64",
        "receipt-missing",
        "tx-failed",
        "tx-in-another-block",
        "receipt-of-another-tx",
        "no-logs",
        "log-of-another-contract",
        "log-of-another-node",
        "log-of-another-epoch",
        "log-of-another-root",
        "quantity-with-leading-zero",
        "status-not-a-quantity",
        "receipt-not-an-object",
        "log-data-not-hex",
    ],
)
def test_an_anchor_the_chain_does_not_hold_as_told_is_refused_naming_what_differs(
    answers: dict[str, Any], match: str
) -> None:
    """``anchor.tx`` and ``anchor.block`` were only the node's word, handed on as verified."""
    document = proof_document()
    rpc, _ = scripted_chain(document, **answers)
    with pytest.raises(ProofVerificationError, match=match):
        verify_record_proof(document, rpc, anchor_log=CONTRACT, record_id="imu-1-3")


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"leaf_index": -1}, "leaf_index"),
        ({"leaf_index": True}, "leaf_index"),
        ({"tree_size": 2**64}, "tree_size"),
        ({"template_root": "AB" * 32}, "template_root"),
        ({"inclusion": ["00" * 32] * 65}, "inclusion"),
        ({"inclusion": ["00" * 31]}, "inclusion[0]"),
        ({"tmt_inclusion": "00"}, "tmt_inclusion"),
        ({"anchor": []}, "anchor"),
        ({"anchor": {"chain_id": 1}}, "anchor.contract"),
        ({"record": {"t": 1}}, "record"),
        ({"epoch": "4"}, "epoch"),
    ],
)
def test_malformed_proof_fields_are_named(change: dict[str, Any], field: str) -> None:
    document = proof_document()
    if field.startswith("anchor.") and change.get("anchor") is not None:
        change = {"anchor": {**document["anchor"], **change["anchor"], "contract": "0x12"}}
    with pytest.raises(ProofFormatError) as refused:
        RecordProof.from_json({**document, **change})
    assert refused.value.field == field


def test_a_parsed_proof_is_its_document_without_what_the_node_added() -> None:
    """``verify --json`` printed the node's whole answer beside ``"verified": true``, so a
    field the proof does not cover (or an ``id`` of another record) read as verified."""
    document = proof_document()
    added = {**document, "id": "other-1-0", "verified": False, "note": "trust me"}
    assert RecordProof.from_json(added).to_json() == document
