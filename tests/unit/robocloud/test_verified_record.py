"""``Storage.verified_record`` and ``robocloud verify`` against a hostile storage node on a real
socket: a proof of another record, of a root the chain does not hold, or a malformed one is
the SDK's documented error naming what is wrong, never a record handed on."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from typing import Any

import pytest
from typer.testing import CliRunner

from robocloud.cli import app
from robocloud.errors import ConflictError, InvalidAnswerError
from robocloud.proofs import ProofFormatError, ProofVerificationError, RecordIdError
from robocloud.storage import Storage
from tests.scripted_http import (
    Exchange,
    Reply,
    Script,
    ScriptedServer,
    json_reply,
    scripted_server,
)
from tests.unit.robocloud.test_proofs import (
    CONTRACT,
    NODE,
    SOUND_CALLS,
    TX,
    anchor_at_answer,
    anchor_receipt,
    proof_document,
    scripted_chain,
)

runner = CliRunner()
SOUND = proof_document()
"""Leaf 3 of imu@1 (``imu-1-3``), in epoch 4 of ``NODE`` on chain 1337."""


def node_answering(body: bytes | str) -> Iterator[ScriptedServer]:
    return scripted_server(lambda _: json_reply(body))


def test_a_sound_proof_gives_the_record_the_chain_vouches_for() -> None:
    rpc, calls = scripted_chain(SOUND)
    with node_answering(json.dumps(SOUND)) as node, Storage(node.url) as storage:
        proof = storage.verified_record("imu-1-3", rpc, anchor_log=CONTRACT, node=NODE)
    assert proof.record == SOUND["record"]
    assert [e.path for e in node.exchanges] == ["/v1/records/imu-1-3/proof"]
    assert calls == [("eth_chainId", []), *SOUND_CALLS]


@pytest.mark.parametrize(
    ("body", "answers", "error", "match"),
    [
        (
            proof_document(index=2),
            {},
            ProofVerificationError,
            "asked for imu-1-3, the proof is of leaf 2 of imu@1",
        ),
        (
            SOUND,
            {"eth_call": anchor_at_answer("00" * 32, block=0)},
            ProofVerificationError,
            f"AnchorLog holds {'00' * 32} for epoch 4",
        ),
        (
            {**SOUND, "anchor": {**SOUND["anchor"], "block": 8}},
            {},
            ProofVerificationError,
            "in block 9, the proof says block 8",
        ),
        (
            SOUND,
            {"eth_getTransactionReceipt": None},
            ProofVerificationError,
            f"no receipt for the anchor's tx {TX}",
        ),
        (
            {**SOUND, "record": {**SOUND["record"], "t": 4}},
            {},
            ProofVerificationError,
            "not in its template log",
        ),
        (
            {k: v for k, v in SOUND.items() if k != "tmt_root"},
            {},
            ProofFormatError,
            "proof field tmt_root: missing",
        ),
        ({**SOUND, "inclusion": "ab" * 32}, {}, ProofFormatError, "proof field inclusion"),
        ([SOUND], {}, ProofFormatError, r"proof field \(document\): not a JSON object"),
    ],
    ids=[
        "another-record",
        "root-not-anchored",
        "block-not-the-anchors",
        "tx-not-mined",
        "changed-record",
        "missing",
        "not-list",
        "list",
    ],
)
def test_a_proof_that_does_not_hold_is_refused_naming_why(
    body: Any, answers: dict[str, Any], error: type[Exception], match: str
) -> None:
    rpc, _ = scripted_chain(SOUND, **answers)
    with (
        node_answering(json.dumps(body)) as node,
        Storage(node.url, retries=0) as storage,
        pytest.raises(error, match=match),
    ):
        storage.verified_record("imu-1-3", rpc, anchor_log=CONTRACT)


def test_an_answer_that_is_not_json_is_an_invalid_answer() -> None:
    rpc, calls = scripted_chain(SOUND)
    with (
        node_answering("<html>proxy login</html>") as node,
        Storage(node.url, retries=0) as storage,
        pytest.raises(InvalidAnswerError),
    ):
        storage.verified_record("imu-1-3", rpc, anchor_log=CONTRACT)
    assert calls == []


def test_the_anchor_must_be_on_the_chain_the_robot_reads() -> None:
    """The node's word for the chain id was handed on as verified; the chain is the rpc's."""
    rpc, _ = scripted_chain(SOUND, chain_id=1)
    with (
        node_answering(json.dumps(SOUND)) as node,
        Storage(node.url) as storage,
        pytest.raises(ProofVerificationError, match="chain 1337, not 1"),
    ):
        storage.verified_record("imu-1-3", rpc, anchor_log=CONTRACT)
    rpc, calls = scripted_chain(SOUND, chain_id=1)
    with node_answering(json.dumps(SOUND)) as node, Storage(node.url) as storage:
        proof = storage.verified_record("imu-1-3", rpc, anchor_log=CONTRACT, chain_id=1337)
    assert proof.anchor.chain_id == 1337
    assert calls == SOUND_CALLS


def test_an_id_that_is_not_a_record_id_is_refused_before_anything_is_sent() -> None:
    rpc, calls = scripted_chain(SOUND)
    with (
        node_answering(json.dumps(SOUND)) as node,
        Storage(node.url) as storage,
        pytest.raises(RecordIdError),
    ):
        storage.verified_record("imu-1-3/../../x", rpc, anchor_log=CONTRACT)
    assert node.exchanges == []
    assert calls == []


def json_rpc(answers: dict[str, Any]) -> Any:
    """A JSON-RPC server's script: the chain of ``scripted_chain(SOUND, **answers)``."""
    request, _ = scripted_chain(SOUND, **answers)

    def script(exchange: Exchange) -> Reply:
        call = json.loads(exchange.body)
        result = request(call["method"], call["params"])
        return json_reply(json.dumps({"jsonrpc": "2.0", "id": call["id"], "result": result}))

    return script


@pytest.mark.parametrize(
    ("answers", "code", "said"),
    [
        ({}, 0, "record   imu-1-3 verified"),
        ({"eth_call": anchor_at_answer("00" * 32, block=0)}, 6, "AnchorLog holds"),
        (
            {"eth_getTransactionReceipt": {**anchor_receipt(SOUND["tmt_root"]), "logs": []}},
            6,
            "has no Anchored log",
        ),
    ],
    ids=["anchored", "not-anchored", "tx-not-the-anchors"],
)
def test_robocloud_verify_says_what_the_sdk_found(
    answers: dict[str, Any], code: int, said: str
) -> None:
    with (
        node_answering(json.dumps(SOUND)) as node,
        scripted_server(json_rpc(answers)) as rpc,
    ):
        urls = ["--storage", node.url, "--rpc", rpc.url]
        trusted = ["--anchor-log", CONTRACT, "--node", NODE]
        result = runner.invoke(app, ["verify", "imu-1-3", *urls, *trusted])
    assert result.exit_code == code, result.output
    assert said in result.output


NOT_ANCHORED = json_reply(
    json.dumps(
        {
            "error": {
                "code": "not_anchored",
                "message": "imu-1-3 is in epoch 4, not anchored yet",
                "details": {"id": "imu-1-3", "epoch": 4},
                "request_id": "r1",
            }
        }
    ),
    status=409,
)


def anchored_after(refusals: int) -> Script:
    """A node whose record is anchored after it refused ``refusals`` asks for its proof."""
    asked = 0

    def answer(_: Exchange) -> Reply:
        nonlocal asked
        asked += 1
        return NOT_ANCHORED if asked <= refusals else json_reply(json.dumps(SOUND))

    return answer


def test_a_record_not_anchored_yet_is_waited_for() -> None:
    """A robot that had just written a record and asked for its proof before the node's
    epoch was anchored (seconds) got 409 not_anchored, and retried by hand."""
    rpc, _ = scripted_chain(SOUND)
    with scripted_server(anchored_after(2)) as node, Storage(node.url) as storage:
        proof = storage.verified_record("imu-1-3", rpc, anchor_log=CONTRACT, node=NODE, wait_s=30)
    assert proof.record == SOUND["record"]
    assert node.count("GET") == 3


@pytest.mark.parametrize("wait_s", [0.0, 0.5])
def test_a_record_still_not_anchored_is_the_conflict(wait_s: float) -> None:
    rpc, calls = scripted_chain(SOUND)
    with scripted_server(anchored_after(1_000)) as node, Storage(node.url) as storage:
        started = time.monotonic()
        with pytest.raises(ConflictError) as refused:
            storage.verified_record("imu-1-3", rpc, anchor_log=CONTRACT, wait_s=wait_s)
        waited_s = time.monotonic() - started
    assert refused.value.code == "not_anchored"
    assert (node.count("GET") == 1) == (wait_s == 0)
    assert wait_s <= waited_s < wait_s + 5
    assert calls == []


def test_another_conflict_is_not_waited_for() -> None:
    conflict = json.loads(NOT_ANCHORED[2])
    conflict["error"]["code"] = "other_conflict"
    rpc, _ = scripted_chain(SOUND)
    reply = json_reply(json.dumps(conflict), status=409)
    with (
        scripted_server(lambda _: reply) as node,
        Storage(node.url) as storage,
        pytest.raises(ConflictError),
    ):
        storage.verified_record("imu-1-3", rpc, anchor_log=CONTRACT, wait_s=30)
    assert node.count("GET") == 1


@pytest.mark.parametrize(("options", "code"), [([], 5), (["--wait", "30"], 0)])
def test_robocloud_verify_waits_or_says_to_retry(options: list[str], code: int) -> None:
    """Exit 4 said "the same request will not succeed" of a record anchored seconds later."""
    with (
        scripted_server(anchored_after(2)) as node,
        scripted_server(json_rpc({})) as rpc,
    ):
        urls = ["--storage", node.url, "--rpc", rpc.url]
        trusted = ["--anchor-log", CONTRACT, "--node", NODE]
        result = runner.invoke(app, ["verify", "imu-1-3", *urls, *trusted, *options])
    assert result.exit_code == code, result.output
    if code:
        assert "409 not_anchored" in result.stderr
        assert "--wait 30" in result.stderr
    else:
        assert "imu-1-3 verified" in result.stdout
