"""External-node mode's event index against a scripted node whose ``eth_getLogs`` lies.

The integration tests (``tests/integration/services/ledger/test_external.py``) follow real
nodes; here the node is a script, so that one field of one log can be made what no honest
node sends, and what the index then stores, refuses and retries can be read back.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from robocloud.errors import InvalidAnswerError
from services.ledger import external
from services.ledger.external import ExternalLedger
from services.ledger.index import LogFilter
from services.ledger.settings import LedgerSettings
from tests.scripted_http import Exchange, Reply, json_reply, scripted_server
from tests.unit.services.ledger.test_index import ANCHOR_LOG, IMPOSTOR, REGISTRY, ROBOT, registered

HEAD = 5
"""The head a test's node grows to, from block 0 where the ledger started: with pages of 2
blocks, a round then asks for blocks 1-2, 3-4 and 5."""


def block_hash(number: int) -> str:
    return "0x" + (number + 0x100).to_bytes(32, "big").hex()


def at(number: int) -> tuple[int, bytes]:
    """The index's cursor at block ``number`` of the node's chain."""
    return number, bytes.fromhex(block_hash(number)[2:])


def rpc_log(block: int, **lies: Any) -> dict[str, Any]:
    """The Registry's ``RobotRegistered`` of ``ROBOT`` in ``block`` as a node sends it, with
    ``lies`` put in place of its fields."""
    honest = registered(block).to_rpc() | {"blockHash": block_hash(block)}
    return honest | lies


@dataclass
class Node:
    """A chain up to block ``head`` whose logs, by block, are ``logs``, unless it ``lies``."""

    head: int = 0
    logs: dict[int, list[Any]] = field(default_factory=dict)
    lies: dict[str, Any] = field(default_factory=dict)
    """Answers to methods, by name, in place of the honest ones."""

    def answer(self, method: str, params: list[Any]) -> Any:
        if method in self.lies:
            return self.lies[method]
        if method == "eth_chainId":
            return "0x539"
        if method == "eth_getCode":
            return "0x6001"
        if method == "eth_call":
            return "0x" + "00" * 32
        if method == "eth_blockNumber":
            return hex(self.head)
        if method == "eth_getBlockByNumber":
            return {"hash": block_hash(int(params[0], 16))}
        if method == "eth_getLogs":
            first, last = (int(params[0][key], 16) for key in ("fromBlock", "toBlock"))
            return [log for block in range(first, last + 1) for log in self.logs.get(block, [])]
        raise AssertionError(f"unexpected {method}")

    def script(self, exchange: Exchange) -> Reply:
        call = json.loads(exchange.body)
        result = self.answer(call["method"], call["params"])
        return json_reply(json.dumps({"jsonrpc": "2.0", "id": call["id"], "result": result}))


@pytest.fixture
def node() -> Node:
    return Node()


def settings(url: str) -> LedgerSettings:
    return LedgerSettings(
        ledger_rpc_url=url,
        ledger_registry_address=REGISTRY,
        ledger_anchor_log_address=ANCHOR_LOG,
        ledger_log_page_blocks=2,
    )


@pytest.fixture
def ledger(tmp_path: Path, node: Node) -> Iterator[ExternalLedger]:
    with scripted_server(node.script) as server:
        opened = ExternalLedger(settings(server.url), tmp_path, None)
        assert opened.index.cursor() == at(0)
        node.head = HEAD
        yield opened
        opened.close()


def indexed_blocks(ledger: ExternalLedger) -> list[int]:
    return [entry.block_number for entry in ledger.index.logs(LogFilter(0, 2**63 - 1))]


def test_an_honest_nodes_logs_are_indexed(node: Node, ledger: ExternalLedger) -> None:
    node.logs = {1: [rpc_log(1)], 3: [rpc_log(3, logIndex="0x1", transactionIndex="0x2")]}
    ledger.poll_once()
    assert ledger.index.cursor() == at(HEAD)
    assert indexed_blocks(ledger) == [1, 3]
    (third,) = ledger.index.logs(LogFilter(3, 3))
    assert (third.log_index, third.tx_index) == (1, 2)
    assert ledger.index.robot(ROBOT) is not None


LIES = {
    "negative-block": ({"blockNumber": "-0x3"}, "blockNumber: '-0x3' is not"),
    "decimal-block": ({"blockNumber": "-5"}, "blockNumber: '-5' is not"),
    "leading-zero": ({"blockNumber": "0x03"}, "blockNumber: '0x03' is not"),
    "block-2^63": ({"blockNumber": hex(2**63)}, r"blockNumber: 9223372036854775808 is past 2\^63"),
    "block-2^64": ({"blockNumber": "0x1" + "0" * 16}, "blockNumber: '0x1000"),
    "tx-index-2^63": ({"transactionIndex": hex(2**63)}, r"transactionIndex: .*past 2\^63 - 1"),
    "log-index-negative": ({"logIndex": "-0x1"}, "logIndex: '-0x1' is not"),
    "log-index-null": ({"logIndex": None}, "logIndex: 'None' is not"),
    "tx-hash-short": ({"transactionHash": "0x" + "ab" * 31}, "transactionHash: '0xabab"),
    "block-hash-8-KiB": ({"blockHash": "0x" + "ab" * 4096}, "blockHash: '0xabab"),
    "address-short": ({"address": "0x" + "11" * 19}, "address: '0x1111"),
    "topic-short": ({"topics": ["0x01"]}, "topics: '0x01' is not"),
    "five-topics": ({"topics": ["0x" + "00" * 32] * 5}, "topics: 5 topics"),
    "data-not-hex": ({"data": "0x zz"}, "data: '0x zz' is not"),
    "another-block": ({"blockNumber": "0x1"}, "block 1, outside the blocks 3 to 4 asked for"),
    "another-contract": ({"address": IMPOSTOR}, f"address {IMPOSTOR}, not one asked for"),
}


@pytest.mark.parametrize(("lie", "message"), LIES.values(), ids=LIES.keys())
def test_a_malformed_log_is_the_nodes_error_and_stores_nothing_of_its_page(
    node: Node, ledger: ExternalLedger, lie: dict[str, Any], message: str
) -> None:
    """``int(x, 16)`` took ``-5`` and numbers of any size: a negative block was stored, and a
    log of block 2^63 raised OverflowError in every round, so the index stopped for good
    with no word of which field was wrong."""
    node.logs = {1: [rpc_log(1)], 3: [rpc_log(3, logIndex="0x1"), rpc_log(3, **lie)]}
    with pytest.raises(InvalidAnswerError, match=message) as refused:
        ledger.poll_once()
    assert len(str(refused.value)) < 400
    assert ledger.index.cursor() == at(2)
    assert indexed_blocks(ledger) == [1]

    node.logs[3] = [rpc_log(3, logIndex="0x1")]
    ledger.poll_once()
    assert ledger.index.cursor() == at(HEAD)
    assert indexed_blocks(ledger) == [1, 3]


@pytest.mark.parametrize("answer", ["logs", [["a list"]], [None]], ids=repr)
def test_logs_that_are_not_log_objects_are_the_nodes_error(
    node: Node, ledger: ExternalLedger, answer: Any
) -> None:
    node.lies["eth_getLogs"] = answer
    with pytest.raises(InvalidAnswerError, match="eth_getLogs"):
        ledger.poll_once()
    assert indexed_blocks(ledger) == []


def test_a_block_hash_that_is_not_a_hash_is_the_nodes_error(
    node: Node, ledger: ExternalLedger
) -> None:
    node.lies["eth_getBlockByNumber"] = {"hash": "0x01"}
    with pytest.raises(InvalidAnswerError, match="block 0's hash: '0x01' is not"):
        ledger.poll_once()
    assert ledger.index.cursor() == at(0)


def test_a_head_past_2_63_is_the_nodes_error(node: Node, ledger: ExternalLedger) -> None:
    node.lies["eth_blockNumber"] = hex(2**63)
    with pytest.raises(
        InvalidAnswerError, match=r"eth_blockNumber: block 9223372036854775808, past 2\^63"
    ):
        ledger.poll_once()
    assert ledger.index.cursor() == at(0)


def test_a_round_refused_at_start_is_logged_and_retried(
    tmp_path: Path, node: Node, caplog: pytest.LogCaptureFixture
) -> None:
    """The first round runs before the service starts serving: a node's lie there must not
    stop the start, only the index, until the node answers well."""
    node.head = HEAD
    node.logs = {1: [rpc_log(1)], 3: [rpc_log(3, blockNumber=hex(2**63))]}
    with scripted_server(node.script) as server:
        with caplog.at_level(logging.ERROR, "robocloud.ledger.external"):
            ledger = ExternalLedger(settings(server.url), tmp_path, None)
        try:
            (record,) = [r for r in caplog.records if r.name == "robocloud.ledger.external"]
            assert "retries" in record.getMessage()
            assert "blockNumber: 9223372036854775808 is past" in record.__dict__["error"]
            assert ledger.index.cursor() == at(1)
            assert indexed_blocks(ledger) == [1]
            node.logs[3] = [rpc_log(3)]
            ledger.index_round()
            assert indexed_blocks(ledger) == [1, 3]
        finally:
            ledger.close()


def test_a_head_far_ahead_is_caught_up_over_bounded_rounds(
    node: Node, ledger: ExternalLedger, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A node that says its head is near 2^63 held the indexing round, and the start and
    shutdown that wait for it, for as many pages as it liked to answer."""
    monkeypatch.setattr(external, "MAX_PAGES_PER_ROUND", 3)
    node.head = 2**63 - 2
    node.logs = {1: [rpc_log(1)], 9: [rpc_log(9)]}
    assert ledger.poll_once() is False
    assert ledger.index.cursor() == at(6)
    assert ledger.index_round() is False
    assert ledger.index.cursor() == at(12)
    assert indexed_blocks(ledger) == [1, 9]
    node.head = 14
    assert ledger.poll_once() is True
    assert ledger.index.cursor() == at(14)
