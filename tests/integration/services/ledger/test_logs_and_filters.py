"""Log queries validated as nodes do, filters, and the block and transaction lookups clients
expect, each side by side with anvil; a web3.py event filter polling by filters."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from web3 import HTTPProvider, Web3

from robocloud.identity import Identity
from tests.integration.services.ledger.conftest import (
    Pair,
    RobotFactory,
    Service,
    call,
    deploying,
    head,
    mined,
    result,
    start_ledger,
)
from tests.rawtx import RawTx

TOPIC = bytes.fromhex("aa" * 32)
# LOG1(topic TOPIC, data = the first calldata word), then stop.
EMITTER = bytes.fromhex("5f355f527f" + TOPIC.hex() + "60205fa100")
# LOG0 with no data as many times as the first calldata word says, then stop.
REPEATER = bytes.fromhex("6000355b801560155760006000a0600190036003565b00")
# Reads the code size of 0x22..22 and writes then clears slot 0.
TOUCHER = bytes.fromhex("73" + "22" * 20 + "3b50" + "6001600055600060005500")


@pytest.fixture(scope="module")
def emitter(pair: Pair) -> tuple[Identity, tuple[str, str]]:
    owner = pair.funded()
    return owner, pair.deploy(owner, deploying(EMITTER))


def emit(url: str, sender: Identity, to: str, word: int) -> str:
    nonce = int(result(url, "eth_getTransactionCount", [sender.address, "latest"]), 16)
    tx = RawTx(nonce=nonce, to=bytes.fromhex(to[2:]), data=word.to_bytes(32, "big"), gas=60_000)
    tx_hash = result(
        url, "eth_sendRawTransaction", [tx.but(max_fee=10**11).sign(bytes(sender.account.key))]
    )
    assert mined(url, tx_hash)["status"] == "0x1"
    return str(tx_hash)


def essence(log: dict[str, Any]) -> tuple[str, tuple[str, ...], str]:
    return log["address"], tuple(log["topics"]), log["data"]


# ----- eth_getLogs validation -----


def errors_of(pair: Pair, query: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    mine = call(pair.ledger, "eth_getLogs", [query])
    node = call(pair.anvil, "eth_getLogs", [query])
    assert "error" in mine, mine
    assert "error" in node, node
    return mine["error"], node["error"]


def test_more_than_four_topics_is_invalid_params_on_both(pair: Pair) -> None:
    mine, node = errors_of(pair, {"topics": [None] * 5})
    assert mine == node == {"code": -32602, "message": "exceeded maximum topics len"}


def test_block_hash_with_a_range_is_invalid_params_on_both(pair: Pair) -> None:
    block_hash = result(pair.ledger, "eth_getBlockByNumber", ["latest", False])["hash"]
    for key in ("fromBlock", "toBlock"):
        mine, node = errors_of(pair, {"blockHash": block_hash, key: "0x0"})
        assert mine == node
        assert mine == {
            "code": -32602,
            "message": "cannot specify both blockHash and fromBlock/toBlock, "
            "choose one or the other",
        }


def test_from_block_beyond_the_head_is_invalid_params_on_both(pair: Pair) -> None:
    for url in pair.urls:
        height = int(result(url, "eth_blockNumber", []), 16)
        error = call(url, "eth_getLogs", [{"fromBlock": hex(height + 10)}])["error"]
        assert error == {
            "code": -32602,
            "message": f"BlockOutOfRangeError: block height is {height} but requested was "
            f"{height + 10}",
        }
        assert (
            result(url, "eth_getLogs", [{"fromBlock": "0x0", "toBlock": hex(height + 10)}])
            is not None
        )


def test_an_empty_block_bound_is_invalid_params_on_both(pair: Pair) -> None:
    """``""`` was read as ``latest``; geth and anvil refuse it."""
    for key in ("fromBlock", "toBlock"):
        mine, node = errors_of(pair, {key: ""})
        assert mine["code"] == node["code"] == -32602, (mine, node)


def test_from_block_zero_as_a_number_is_block_zero(pair: Pair) -> None:
    """A JSON number, which the ledger takes where geth and anvil want ``0x``-hex, was read by
    its truth: ``fromBlock: 0`` answered only the head's logs."""
    sender = pair.funded()
    address, _ = pair.deploy(sender, deploying(EMITTER))
    hashes = [emit(pair.ledger, sender, address, word) for word in (3, 4)]
    query = {"address": address, "toBlock": "latest"}
    by_number = result(pair.ledger, "eth_getLogs", [{**query, "fromBlock": 0}])
    assert by_number == result(pair.ledger, "eth_getLogs", [{**query, "fromBlock": "0x0"}])
    assert [log["transactionHash"] for log in by_number][-2:] == hashes
    assert len(result(pair.ledger, "eth_getLogs", [{**query, "fromBlock": None}])) == 1


def test_an_unknown_block_hash_is_unknown_block_on_both(pair: Pair) -> None:
    mine, node = errors_of(pair, {"blockHash": "0x" + "00" * 32})
    assert mine == node == {"code": -32000, "message": "unknown block"}


def test_queries_wider_than_the_bound_are_refused(pair: Pair) -> None:
    addresses = ["0x" + f"{n:040x}" for n in range(1001)]
    error = call(pair.ledger, "eth_getLogs", [{"address": addresses}])["error"]
    assert error == {"code": -32602, "message": "too many addresses: at most 1000"}
    topics = [["0x" + f"{n:064x}" for n in range(1001)]]
    error = call(pair.ledger, "eth_getLogs", [{"topics": topics}])["error"]
    assert error == {"code": -32602, "message": "too many topics at one position: at most 1000"}


# ----- filters -----


def test_filters_report_the_same_changes_as_anvil(
    pair: Pair, emitter: tuple[Identity, tuple[str, str]]
) -> None:
    sender, contracts = emitter
    seen = []
    for url, address in zip(pair.urls, contracts, strict=True):
        start = int(result(url, "eth_blockNumber", []), 16)
        logs_filter = result(url, "eth_newFilter", [{"address": address, "fromBlock": hex(start)}])
        topic_filter = result(url, "eth_newFilter", [{"topics": [None]}])
        blocks_filter = result(url, "eth_newBlockFilter", [])
        assert result(url, "eth_getFilterChanges", [logs_filter]) == []
        hashes = [emit(url, sender, address, word) for word in (7, 8)]
        receipts = [mined(url, h) for h in hashes]
        changes = result(url, "eth_getFilterChanges", [logs_filter])
        assert [log["transactionHash"] for log in changes] == hashes
        assert result(url, "eth_getFilterChanges", [logs_filter]) == []
        assert result(url, "eth_getFilterLogs", [logs_filter]) == changes
        assert len(result(url, "eth_getFilterChanges", [topic_filter])) == 2
        blocks = result(url, "eth_getFilterChanges", [blocks_filter])
        assert blocks == [receipt["blockHash"] for receipt in receipts]
        assert result(url, "eth_getFilterChanges", [blocks_filter]) == []
        block_logs = call(url, "eth_getFilterLogs", [blocks_filter])["error"]
        assert block_logs == {"code": -32000, "message": "filter not found"}
        assert result(url, "eth_uninstallFilter", [logs_filter]) is True
        assert result(url, "eth_uninstallFilter", [logs_filter]) is False
        gone = call(url, "eth_getFilterChanges", [logs_filter])["error"]
        assert gone == {"code": -32000, "message": "filter not found"}
        seen.append([essence(log) for log in changes])
    assert seen[0] == seen[1]


def test_a_filter_moves_on_past_ten_thousand_logs_as_anvil_reports_them(pair: Pair) -> None:
    """A filter whose blocks held more than 10,000 logs answered -32005 at every poll and
    never moved, and a block of more than 10,000 could never be read. A poll now answers
    whole blocks up to 10,000 logs (the first block whole, however many it holds) and the
    rest at the next polls; anvil answers everything at once: the same logs in all."""
    owner = pair.funded()
    contracts = pair.deploy(owner, deploying(REPEATER))
    counts = (6_000, 6_000, 10_001)
    reported = []
    for url, address in zip(pair.urls, contracts, strict=True):
        filter_id = result(url, "eth_newFilter", [{"address": address}])
        blocks = []
        for count in counts:
            nonce = int(result(url, "eth_getTransactionCount", [owner.address, "latest"]), 16)
            tx = RawTx(nonce=nonce, to=bytes.fromhex(address[2:]), data=count.to_bytes(32, "big"))
            raw = tx.but(gas=5_000_000, max_fee=10**10).sign(bytes(owner.account.key))
            tx_hash = result(url, "eth_sendRawTransaction", [raw])
            blocks.append(mined(url, tx_hash)["blockHash"])
        polls = []
        while changes := result(url, "eth_getFilterChanges", [filter_id]):
            polls.append(changes)
        if url == pair.ledger:
            assert [len(poll) for poll in polls] == list(counts)
            whole = call(url, "eth_getLogs", [{"address": address, "fromBlock": "0x0"}])
            assert whole["error"]["code"] == -32005
        else:
            assert [len(poll) for poll in polls] == [sum(counts)]
        big = result(url, "eth_getLogs", [{"blockHash": blocks[-1]}])
        assert len(big) == counts[-1]
        reported.append([(log["logIndex"], *essence(log)[1:]) for poll in polls for log in poll])
        assert [log["blockHash"] for poll in polls for log in poll] == [
            block for block, count in zip(blocks, counts, strict=True) for _ in range(count)
        ]
    assert reported[0] == reported[1]


def test_a_filter_starting_beyond_the_head_is_refused_on_both(pair: Pair) -> None:
    for url in pair.urls:
        height = int(result(url, "eth_blockNumber", []), 16)
        error = call(url, "eth_newFilter", [{"fromBlock": hex(height + 5)}])["error"]
        assert error["code"] == -32602
        assert error["message"].startswith("BlockOutOfRangeError")


def test_web3_event_filter_works_by_filters(service: Service, robot: RobotFactory) -> None:
    w3 = Web3(HTTPProvider(f"{service.url}/rpc"))
    described = httpx.get(f"{service.url}/v1/contracts").json()["contracts"]["Registry"]
    registry = w3.eth.contract(address=described["address"], abi=described["abi"])
    start = w3.eth.block_number
    events = registry.events.RobotRegistered.create_filter(from_block=start)
    blocks = w3.eth.filter("latest")
    first, second = robot(), robot()
    assert first.identity is not None
    assert second.identity is not None
    registered = [entry["args"]["robot"] for entry in events.get_new_entries()]
    assert registered == [first.identity.address, second.identity.address]
    assert events.get_new_entries() == []
    assert [e["args"]["robot"] for e in events.get_all_entries()] == registered
    assert len(blocks.get_new_entries()) >= 4  # two faucet grants and two registrations
    assert w3.eth.uninstall_filter(events.filter_id)
    latest_only = registry.events.RobotRegistered.create_filter(from_block="latest")
    assert [e["args"]["robot"] for e in latest_only.get_all_entries()] == registered[1:]


@pytest.fixture(scope="module")
def few_filters(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    process = start_ledger(
        tmp_path_factory.mktemp("filters") / "data",
        {
            "ROBOCLOUD_LEDGER_MAX_FILTERS": "2",
            "ROBOCLOUD_LEDGER_MAX_FILTERS_PER_CLIENT": "2",
            "ROBOCLOUD_LEDGER_FILTER_TIMEOUT_S": "600",
        },
    )
    try:
        yield f"{process.url}/rpc"
    finally:
        process.stop()


def test_filters_are_bounded_in_number(few_filters: str) -> None:
    first = result(few_filters, "eth_newBlockFilter", [])
    result(few_filters, "eth_newFilter", [{}])
    error = call(few_filters, "eth_newBlockFilter", [])["error"]
    assert error == {
        "code": -32000,
        "message": "too many filters: at most 2 at once; uninstall filters no longer polled",
    }
    assert result(few_filters, "eth_getFilterChanges", [first]) == []
    assert result(few_filters, "eth_uninstallFilter", [first]) is True
    assert result(few_filters, "eth_newBlockFilter", []).startswith("0x")


def test_one_client_address_holds_only_its_share_of_the_filters(
    tmp_path: Path,
) -> None:
    """Clients told apart by the address they connect from (127.0.0.2 and 127.0.0.3 reach the
    ledger on 127.0.0.1): one installing filters in a loop fills its share, not the node."""
    process = start_ledger(
        tmp_path / "data",
        {"ROBOCLOUD_LEDGER_MAX_FILTERS": "3", "ROBOCLOUD_LEDGER_MAX_FILTERS_PER_CLIENT": "2"},
    )
    url = f"{process.url}/rpc"
    request = {"jsonrpc": "2.0", "id": 1, "method": "eth_newBlockFilter", "params": []}
    try:
        with (
            httpx.Client(transport=httpx.HTTPTransport(local_address="127.0.0.2")) as greedy,
            httpx.Client(transport=httpx.HTTPTransport(local_address="127.0.0.3")) as other,
        ):
            installed = [greedy.post(url, json=request).json()["result"] for _ in range(2)]
            assert greedy.post(url, json=request).json()["error"] == {
                "code": -32000,
                "message": "too many filters from one client: at most 2 at once; uninstall "
                "filters no longer polled",
            }
            assert other.post(url, json=request).json()["result"].startswith("0x")
            assert result(url, "eth_getFilterChanges", [installed[0]]) == []
            assert "at most 3 at once" in call(url, "eth_newBlockFilter", [])["error"]["message"]
    finally:
        process.stop()


@pytest.mark.parametrize("value", [7, "0x", "nothex", "0x" + "1" * 100])
def test_bad_filter_ids_change_nothing(few_filters: str, value: Any) -> None:
    for method in ("eth_getFilterChanges", "eth_getFilterLogs", "eth_uninstallFilter"):
        answer = call(few_filters, method, [value])
        if "error" in answer:
            assert answer["error"]["code"] in (-32602, -32000)
        else:
            assert answer["result"] is False


# ----- blocks, transactions, receipts -----


def test_block_lookups_agree_with_anvil(
    pair: Pair, emitter: tuple[Identity, tuple[str, str]]
) -> None:
    sender, contracts = emitter
    for url, address in zip(pair.urls, contracts, strict=True):
        tx_hash = emit(url, sender, address, 9)
        receipt = mined(url, tx_hash)
        number, block_hash = receipt["blockNumber"], receipt["blockHash"]
        assert result(url, "eth_getBlockReceipts", [number]) == [receipt]
        assert result(url, "eth_getBlockReceipts", ["latest"]) == [receipt]
        assert result(url, "eth_getBlockReceipts", [{"blockHash": block_hash}]) == [receipt]
        assert result(url, "eth_getBlockTransactionCountByNumber", [number]) == "0x1"
        assert result(url, "eth_getBlockTransactionCountByHash", [block_hash]) == "0x1"
        transaction = result(url, "eth_getTransactionByHash", [tx_hash])
        by_number = result(url, "eth_getTransactionByBlockNumberAndIndex", [number, "0x0"])
        by_hash = result(url, "eth_getTransactionByBlockHashAndIndex", [block_hash, "0x0"])
        assert by_number == by_hash == transaction
        assert result(url, "eth_getTransactionByBlockNumberAndIndex", [number, "0x1"]) is None
        missing = hex(int(result(url, "eth_blockNumber", []), 16) + 100)
        assert result(url, "eth_getBlockTransactionCountByHash", ["0x" + "00" * 32]) is None
        assert (
            result(url, "eth_getTransactionByBlockHashAndIndex", ["0x" + "00" * 32, "0x0"]) is None
        )
        if url == pair.ledger:  # anvil refuses a number past its head; geth answers null
            assert result(url, "eth_getBlockReceipts", [missing]) is None
            assert result(url, "eth_getBlockTransactionCountByNumber", [missing]) is None


def test_create_access_list_agrees_with_anvil(pair: Pair) -> None:
    owner = pair.funded()
    contracts = pair.deploy(owner, deploying(TOUCHER))
    answers = []
    for url, address in zip(pair.urls, contracts, strict=True):
        request = {"from": owner.address, "to": address}
        found = result(url, "eth_createAccessList", [request, "latest"])
        assert found["accessList"] == [
            {"address": "0x" + "22" * 20, "storageKeys": []},
            {"address": address.lower(), "storageKeys": ["0x" + "00" * 32]},
        ] or found["accessList"] == [
            {"address": address.lower(), "storageKeys": ["0x" + "00" * 32]},
            {"address": "0x" + "22" * 20, "storageKeys": []},
        ]
        answers.append(found)
    assert sorted(answers[0]["accessList"], key=str) == sorted(answers[1]["accessList"], key=str)
    assert answers[0]["gasUsed"] == answers[1]["gasUsed"]


def test_small_methods_agree_with_anvil(pair: Pair) -> None:
    for method, params in [
        ("web3_sha3", ["0x68656c6c6f"]),
        ("web3_sha3", ["0x"]),
        ("eth_coinbase", []),
    ]:
        assert result(pair.ledger, method, params) == result(pair.anvil, method, params)
    assert result(pair.ledger, "eth_protocolVersion", []) == "0x44"
    assert call(pair.ledger, "web3_sha3", ["zz"])["error"]["code"] == -32602
    assert call(pair.anvil, "web3_sha3", ["zz"])["error"]["code"] == -32602


def test_filters_are_read_only(service: Service) -> None:
    """Installing and polling filters mines nothing."""
    before = head(service.url)
    # Up to block 1 (the Registry's deployment logs): the module's chain holds more than
    # 10,000 logs in all, which eth_getFilterLogs refuses as eth_getLogs does.
    query = {"fromBlock": "0x0", "toBlock": "0x1"}
    filter_id = result(f"{service.url}/rpc", "eth_newFilter", [query])
    assert len(result(f"{service.url}/rpc", "eth_getFilterLogs", [filter_id])) > 0
    assert result(f"{service.url}/rpc", "eth_getFilterChanges", [filter_id]) == []
    assert head(service.url) == before
