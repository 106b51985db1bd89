"""Record ids and proof documents: parsing refuses every malformed field; hashes are checked."""

from __future__ import annotations

from typing import Any

import pytest
from eth_utils.crypto import keccak

from robocloud import jcs, merkle
from robocloud.ledger.abi import ContractAbi
from robocloud.proofs import (
    ROOT_AT_SELECTOR,
    ProofFormatError,
    ProofVerificationError,
    RecordId,
    RecordIdError,
    RecordProof,
    root_at_call,
    verify_record_proof,
)
from services.storage.tmt import EpochTree, TemplateHead

NODE = "0x" + "12" * 20
CONTRACT = "0x" + "34" * 20


def test_the_selector_is_anchorlogs_root_at() -> None:
    assert keccak(text="rootAt(address,uint64)")[:4] == ROOT_AT_SELECTOR
    abi = ContractAbi.load("AnchorLog")
    assert (
        root_at_call(CONTRACT, NODE, 7)["data"] == "0x" + abi.encode_call("rootAt", NODE, 7).hex()
    )


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
            "tx": "0x" + "ab" * 32,
            "block": 9,
        },
    }


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
    calls: list[tuple[str, list[Any]]] = []

    def chain(answer: str) -> Any:
        def request(method: str, params: list[Any]) -> Any:
            calls.append((method, params))
            return answer

        return request

    verified = verify_record_proof(
        document, chain("0x" + document["tmt_root"]), anchor_log=CONTRACT, record_id="imu-1-3"
    )
    assert verified.leaf_index == 3
    assert calls == [("eth_call", [root_at_call(CONTRACT, NODE, 4), "latest"])]
    with pytest.raises(ProofVerificationError, match="AnchorLog holds 0000"):
        verify_record_proof(document, chain("0x" + "00" * 32), anchor_log=CONTRACT)
    with pytest.raises(ProofVerificationError, match="not a bytes32"):
        verify_record_proof(document, chain("0x"), anchor_log=CONTRACT)
    with pytest.raises(ProofVerificationError, match="chain 1337, not 1"):
        verify_record_proof(document, chain("0x"), anchor_log=CONTRACT, chain_id=1)


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
