"""What the anchorer records as an epoch's anchor, from a JSON-RPC node that lies.

The record (chain id, contract, transaction, block) is published with every proof of the
epoch and never revisited: an epoch marked anchored with another node's transaction, another
chain or a made-up block leaves every proof of it failing for good.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import httpx
import pytest
from eth_abi.abi import encode
from eth_utils.crypto import keccak

from robocloud.errors import InvalidAnswerError
from robocloud.identity import Identity
from robocloud.ledger import Anchor, Ledger, SignedTransaction
from robocloud.ledger.client import ContractAddresses
from robocloud.ledger.rpc import JsonRpcClient
from robocloud.proofs import AnchorRef
from services.storage.anchoring import (
    SCHEMA,
    AnchorConflict,
    Anchorer,
    EpochStore,
    LedgerAndCas,
)
from services.storage.identity import NodeIdentity, Standing
from services.storage.recordlog import RecordLogs
from services.storage.tmt import EpochTree, TemplateHead
from tests.ledger_logs import anchored_log

REGISTRY = "0x" + "22" * 20
ANCHOR_LOG = "0x" + "33" * 20
OTHER_NODE = "0x" + "44" * 20
ANCHORED_AT = 1_700_000_000
BLOCK = 9
Answers = dict[str, Callable[[list[Any]], Any]]
TREE = EpochTree.build(1, [TemplateHead("state", 3, b"\x01" * 32)])
TX = "0x" + "ab" * 32


class Cas:
    def add_bytes(self, data: bytes) -> str:
        return "bafkmanifest"


def holding_the_root(block: int = BLOCK, **answers: Callable[[list[Any]], Any]) -> Answers:
    """A node whose ``anchorAt`` holds ``TREE``'s root as the node's epoch 1, in ``block``
    (a crash after mining, before recording), answering ``answers`` besides."""
    values = [TREE.root, TREE.record_count, ANCHORED_AT, block]
    result = "0x" + encode(["bytes32", "uint64", "uint64", "uint64"], values).hex()
    return {"eth_chainId": lambda _: hex(1337), "eth_call": lambda _: result, **answers}


def rpc(answers: Answers) -> JsonRpcClient:
    def handle(request: httpx.Request) -> httpx.Response:
        call = json.loads(request.content)
        result = answers[call["method"]](call["params"])
        return httpx.Response(200, json={"jsonrpc": "2.0", "id": call["id"], "result": result})

    return JsonRpcClient("http://node/rpc", transport=httpx.MockTransport(handle), retries=0)


@pytest.fixture
def anchorer(tmp_path: Path) -> Iterator[Callable[..., Anchorer]]:
    """An anchorer signing with ``identity`` (a new one by default) whose epoch 1 is
    ``TREE``, cut and pending, on a node answering ``answers``."""
    opened: list[Any] = []

    def make(answers: Answers, identity: Identity | None = None) -> Anchorer:
        identity = identity or Identity.generate()
        logs = RecordLogs(tmp_path / "logs")
        epochs = EpochStore(tmp_path / "epochs.sqlite", identity.address)
        assert epochs.cut(list(TREE.heads)) == TREE
        ledger = Ledger(rpc(answers), ContractAddresses(REGISTRY, ANCHOR_LOG), identity)
        chain = LedgerAndCas(ledger, Cas())
        anchorer = Anchorer(
            logs,
            epochs,
            NodeIdentity(identity),
            lambda: chain,
            epoch_s=60,
            epoch_records=1000,
            retry_s=1,
            register=False,
        )
        anchorer.standing = Standing.ANCHORING
        opened.extend([chain, epochs, logs])
        return anchorer

    yield make
    for thing in opened:
        thing.close()


def recorded(anchorer: Anchorer) -> AnchorRef | None:
    """What the anchorer recorded as epoch 1's anchor."""
    epoch = anchorer.epochs.get(1)
    assert epoch is not None
    return epoch.anchor


def own_anchor(address: str) -> Anchor:
    """``address``'s anchor of ``TREE`` as epoch 1, in ``BLOCK`` by transaction ``TX``."""
    return Anchor(address, 1, TREE.root, TREE.record_count, ANCHORED_AT, BLOCK, TX)


def own_log(address: str, **changes: Any) -> dict[str, Any]:
    """The Anchored event of ``own_anchor(address)``, with ``changes`` to its fields."""
    return anchored_log(ANCHOR_LOG, replace(own_anchor(address), **changes))


def test_a_root_found_on_chain_is_recorded_with_its_own_event(
    anchorer: Callable[..., Anchorer],
) -> None:
    queries: list[Any] = []

    def logs(params: list[Any]) -> list[Any]:
        queries.append(params[0])
        return [own_log(node.node.address)]

    node = anchorer(holding_the_root(eth_getLogs=logs))
    assert node.anchor_next()
    assert recorded(node) == AnchorRef(1337, ANCHOR_LOG, node.node.address, 1, TX, BLOCK)
    assert [(q["fromBlock"], q["toBlock"]) for q in queries] == [(hex(BLOCK), hex(BLOCK))]


@pytest.mark.parametrize(
    "changes",
    [
        {"node": OTHER_NODE, "epoch": 77, "block_number": BLOCK - 1},
        {"block_number": BLOCK + 1},
        {"root": b"\xee" * 32},
        {"record_count": 999},
    ],
    ids=["another-nodes-anchor", "a-later-block", "another-root", "another-count"],
)
def test_an_event_that_is_not_the_nodes_anchor_is_never_recorded(
    anchorer: Callable[..., Anchorer], changes: dict[str, Any]
) -> None:
    """The node's eth_getLogs answered another node's anchor (epoch 77, a block before
    fromBlock, transaction 0xabab...), which was recorded as this node's for good."""
    lie: list[dict[str, Any]] = []
    node = anchorer(holding_the_root(eth_getLogs=lambda _: lie))
    lie.append(own_log(node.node.address, **changes))
    with pytest.raises(
        (InvalidAnswerError, AnchorConflict), match=r"differ|outside|no Anchored event of this"
    ):
        node.anchor_next()
    assert recorded(node) is None


def test_the_anchorer_checks_the_event_whatever_the_sdk_lets_through(
    anchorer: Callable[..., Anchorer], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The anchorer took any event of its root and block, leaving node and epoch to the
    filter's checks."""
    node = anchorer(holding_the_root())
    own = own_anchor(node.node.address)
    for other in (replace(own, node=OTHER_NODE), replace(own, epoch=77)):
        monkeypatch.setattr(Ledger, "anchors", lambda *_, found=other, **__: [found])
        with pytest.raises(AnchorConflict, match="no Anchored event of this node"):
            node.anchor_next()
    assert recorded(node) is None


ANCHORING_NODE = Identity.generate()


def anchoring(chain_ids: list[int], block: int = BLOCK, log_block: int | None = None) -> Answers:
    """A node holding nothing for epoch 1 that mines the anchor in ``block``, its event in
    ``log_block`` (the same by default), and answers ``eth_chainId`` with ``chain_ids`` in
    turn (the last for good)."""
    empty = "0x" + encode(["bytes32", "uint64", "uint64", "uint64"], [bytes(32), 0, 0, 0]).hex()

    def chain_id(_: list[Any]) -> str:
        return hex(chain_ids.pop(0) if len(chain_ids) > 1 else chain_ids[0])

    def receipt(params: list[Any]) -> dict[str, Any]:
        mined = block if log_block is None else log_block
        log = own_log(ANCHORING_NODE.address, block_number=mined, tx_hash=params[0])
        return {
            "transactionHash": params[0],
            "blockNumber": hex(block),
            "blockHash": "0x" + "cd" * 32,
            "status": "0x1",
            "gasUsed": "0x5208",
            "logs": [log],
        }

    return {
        "eth_chainId": chain_id,
        "eth_call": lambda _: empty,
        "eth_estimateGas": lambda _: hex(100_000),
        "eth_gasPrice": lambda _: hex(10**9),
        "eth_getTransactionCount": lambda _: "0x0",
        "eth_sendRawTransaction": lambda params: "0x" + keccak(hexstr=params[0]).hex(),
        "eth_getTransactionReceipt": receipt,
    }


def test_an_anchor_is_recorded_with_the_chain_it_was_signed_for(
    anchorer: Callable[..., Anchorer],
) -> None:
    """The anchorer asked eth_chainId again after sending and recorded the second answer
    (chain 1) beside a transaction signed for 1337: every proof of the epoch then failed."""
    node = anchorer(anchoring([1337, 1]), identity=ANCHORING_NODE)
    assert node.anchor_next()
    anchor = recorded(node)
    assert anchor is not None
    assert (anchor.chain_id, anchor.block) == (1337, BLOCK)


def test_an_event_of_another_block_than_the_receipts_is_never_recorded(
    anchorer: Callable[..., Anchorer],
) -> None:
    node = anchorer(anchoring([1337], log_block=BLOCK + 1), identity=ANCHORING_NODE)
    with pytest.raises(InvalidAnswerError, match="block differ"):
        node.anchor_next()
    assert recorded(node) is None


def test_a_chain_id_sqlite_cannot_hold_is_refused_before_sending(
    anchorer: Callable[..., Anchorer],
) -> None:
    """Chain id 2^63 was signed for and sent, then recording the anchor raised OverflowError
    at every retry."""

    def send(_: list[Any]) -> str:
        pytest.fail("the anchor was sent")

    node = anchorer({**anchoring([2**63]), "eth_sendRawTransaction": send}, identity=ANCHORING_NODE)
    with pytest.raises(InvalidAnswerError, match="EIP-2294"):
        node.anchor_next()
    assert recorded(node) is None


def honest_after_sending() -> Answers:
    """The honest node after the anchor of ``ANCHORING_NODE`` was mined in ``BLOCK``."""
    return holding_the_root(eth_getLogs=lambda _: [own_log(ANCHORING_NODE.address)])


@pytest.mark.parametrize("block", [2**63, 2**64 - 1], ids=hex)
@pytest.mark.parametrize("where", ["receipt", "anchorAt"])
def test_a_block_sqlite_cannot_hold_is_refused_until_an_honest_node_shows_the_anchor(
    anchorer: Callable[..., Anchorer], where: str, block: int
) -> None:
    """A block past 2^63 - 1 (a uint64, in a receipt and its event, or in anchorAt after a
    crash) was taken: recording it raised OverflowError, after the anchor was sent, at every
    retry. It is refused as the node's answer, nothing is recorded, and the next attempt
    records the anchor from an honest node."""
    if where == "receipt":
        answers = anchoring([1337], block=block)
    else:
        lie = [own_log(ANCHORING_NODE.address, block_number=block)]
        answers = holding_the_root(block, eth_getLogs=lambda _: lie)
    node = anchorer(answers, identity=ANCHORING_NODE)
    with pytest.raises(InvalidAnswerError, match=f"block {block}, past 2\\^63 - 1"):
        node.anchor_next()
    assert recorded(node) is None
    answers.update(honest_after_sending())
    assert node.anchor_next()
    assert recorded(node) == AnchorRef(1337, ANCHOR_LOG, ANCHORING_NODE.address, 1, TX, BLOCK)


def test_the_last_block_sqlite_holds_is_recorded(anchorer: Callable[..., Anchorer]) -> None:
    node = anchorer(anchoring([1337], block=2**63 - 1), identity=ANCHORING_NODE)
    assert node.anchor_next()
    anchor = recorded(node)
    assert anchor is not None
    assert anchor.block == 2**63 - 1


def test_the_epochs_waiting_for_their_anchor_are_found_through_an_index(tmp_path: Path) -> None:
    """The anchorer asks for them before every anchor; a scan of every epoch ever cut grew
    without end (251 ms at 500,000 epochs), and an index made by the old schema's store is
    added when it opens."""
    path = tmp_path / "epochs.sqlite"
    epochs = EpochStore(path, Identity.generate().address)
    assert epochs.cut(list(TREE.heads)) == TREE
    epochs._db.execute("DROP INDEX epochs_pending")
    epochs.close()
    reopened = EpochStore(path, Identity.generate().address)
    plan = reopened._db.execute(
        "EXPLAIN QUERY PLAN SELECT epoch FROM epochs WHERE tx IS NULL ORDER BY epoch"
    ).fetchall()
    assert "epochs_pending" in " ".join(str(step[-1]) for step in plan)
    assert reopened.pending() == [1]
    reopened.close()


def test_a_saved_anchor_transaction_survives_a_reopen_of_an_old_database(
    tmp_path: Path,
) -> None:
    """An ``epochs.sqlite`` from before ``anchor_tx`` gets the column when opened; the saved
    transaction is read back as signed, and cleared once the epoch is recorded anchored."""
    path = tmp_path / "epochs.sqlite"
    old = sqlite3.connect(path)
    old.executescript(SCHEMA.replace(",\n    anchor_tx TEXT", ""))
    old.close()
    node = Identity.generate().address
    epochs = EpochStore(path, node)
    assert epochs.cut(list(TREE.heads)) == TREE
    signed = SignedTransaction(b"\x02\xf8\x01\x02", 7)
    epochs.set_anchor_tx(1, signed)
    epochs.close()
    reopened = EpochStore(path, node)
    assert reopened.anchor_tx(1) == signed
    reopened.set_anchored(1, 1337, ANCHOR_LOG, TX, BLOCK)
    assert reopened.anchor_tx(1) is None
    assert reopened.pending() == []
    reopened.close()


class Crash(Exception):
    """The node dying while it waits for the receipt."""


def test_an_anchor_saved_before_a_crash_is_resumed_not_signed_anew(
    anchorer: Callable[..., Anchorer],
) -> None:
    """Behind an external node the anchor can still be pending when the node dies, where
    ``anchorAt`` does not see it: the restarted anchorer signed another (the next nonce,
    reverted once the first was mined). The transaction is saved before it is sent, and the
    next attempt takes its receipt, nothing estimated or signed again."""
    answers = anchoring([1337])
    mined = answers["eth_getTransactionReceipt"]
    sent: list[str] = []

    def send(params: list[Any]) -> str:
        sent.append(params[0])
        return "0x" + keccak(hexstr=params[0]).hex()

    def crash(_: list[Any]) -> Any:
        raise Crash

    answers.update(eth_sendRawTransaction=send, eth_getTransactionReceipt=crash)
    node = anchorer(answers, identity=ANCHORING_NODE)
    with pytest.raises(Crash):
        node.anchor_next()
    saved = node.epochs.anchor_tx(1)
    assert saved is not None
    assert sent == ["0x" + saved.raw.hex()]

    def estimate(_: list[Any]) -> Any:
        pytest.fail("another anchor was signed")

    answers.update(eth_estimateGas=estimate, eth_getTransactionReceipt=mined)
    assert node.anchor_next()
    anchor = recorded(node)
    assert anchor is not None
    assert anchor.tx == saved.tx_hash
    assert node.epochs.anchor_tx(1) is None
    assert len(sent) == 1
