"""The event index in process, on a real SQLite file: fed logs, it answers as the chain would."""

from __future__ import annotations

import logging
import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from eth_abi import encode
from eth_utils.address import to_checksum_address

from robocloud.ledger.abi import ContractAbi
from services.ledger import index as index_module
from services.ledger.encoding import LogEntry
from services.ledger.index import (
    MAX_LOG_RESULTS,
    SCHEMA,
    EventIndex,
    IndexLimitError,
    LogFilter,
)

REGISTRY = "0x" + "11" * 20
ANCHOR_LOG = "0x" + "22" * 20
IMPOSTOR = "0x" + "33" * 20
ROBOT = to_checksum_address("0x" + "ab" * 20)
METADATA = bytes.fromhex("01551220") + bytes(32)
ABI = ContractAbi.load("Registry")
ANCHOR_ABI = ContractAbi.load("AnchorLog")
UINT64_MAX = 2**64 - 1


@pytest.fixture
def index(tmp_path: Path) -> Iterator[EventIndex]:
    opened = EventIndex(tmp_path / "index.sqlite", REGISTRY, ANCHOR_LOG)
    yield opened
    opened.close()


def log(
    event: str,
    block: int,
    *,
    at: str = REGISTRY,
    position: int = 0,
    abi: ContractAbi = ABI,
    **args: Any,
) -> LogEntry:
    """An event log of ``abi`` (the Registry's unless told), encoded as the EVM emits it."""
    inputs = abi.events[event]["inputs"]
    topics = [abi.event_topic(event)]
    topics += [encode([p["type"]], [args[p["name"]]]) for p in inputs if p["indexed"]]
    plain = [p for p in inputs if not p["indexed"]]
    data = encode([p["type"] for p in plain], [args[p["name"]] for p in plain])
    return LogEntry(
        block_number=block,
        block_hash=block.to_bytes(32, "big"),
        tx_hash=(block * 1000 + position).to_bytes(32, "big"),
        tx_index=0,
        log_index=position,
        address=bytes.fromhex(at[2:]),
        topics=tuple(topics),
        data=data,
    )


def registered(block: int, robot: str = ROBOT, at: str = REGISTRY, position: int = 0) -> LogEntry:
    return log(
        "RobotRegistered",
        block,
        at=at,
        position=position,
        robot=robot,
        metadataCid=METADATA,
        timestamp=block,
    )


def test_a_registration_makes_a_robot_and_moves_the_cursor(index: EventIndex) -> None:
    assert index.cursor() is None
    index.add_block(1, (1).to_bytes(32, "big"), [registered(1)])
    assert index.cursor() == (1, (1).to_bytes(32, "big"))
    robot = index.robot(ROBOT)
    assert robot is not None
    assert (robot["metadata_cid"], robot["registered_block"], robot["active"]) == (
        METADATA,
        1,
        True,
    )


def test_a_look_alike_event_from_another_contract_registers_nobody(index: EventIndex) -> None:
    index.add_block(1, bytes(32), [registered(1, at=IMPOSTOR)])
    assert index.robot(ROBOT) is None
    assert len(index.logs(LogFilter(0, 1))) == 1


def test_pending_registrations_come_and_go(index: EventIndex) -> None:
    asked = log("RegistrationRequested", 1, robot=ROBOT, metadataCid=METADATA, timestamp=7)
    index.add_block(1, bytes(32), [asked])
    assert [row["address"] for row in index.pending()] == [ROBOT]
    assert index.robot(ROBOT) is None
    approved = log("RegistrationApproved", 2, robot=ROBOT, registrar=REGISTRY)
    index.add_block(2, bytes(32), [approved, registered(2)])
    assert index.pending() == []
    assert index.robot(ROBOT) is not None


def test_logs_filter_by_address_and_topics(index: EventIndex) -> None:
    other = to_checksum_address("0x" + "cd" * 20)
    index.add_block(1, bytes(32), [registered(1)])
    index.add_block(2, bytes(32), [registered(2, other)])
    topic = ABI.event_topic("RobotRegistered")
    robot_topic = encode(["address"], [other])
    found = index.logs(LogFilter(0, 2, (bytes.fromhex(REGISTRY[2:]),), ((topic,), (robot_topic,))))
    assert [entry.block_number for entry in found] == [2]
    assert index.logs(LogFilter(3, 9)) == []


def test_rewind_forgets_later_blocks_and_rederives_the_state(index: EventIndex) -> None:
    index.add_block(1, bytes(32), [registered(1)])
    suspended = log("RobotSuspensionChanged", 2, robot=ROBOT, suspended=True)
    index.add_block(2, bytes(32), [suspended])
    assert index.robot(ROBOT)["suspended"] is True  # type: ignore[index]
    index.rewind(1, (1).to_bytes(32, "big"))
    assert index.robot(ROBOT)["suspended"] is False  # type: ignore[index]
    assert index.cursor() == (1, (1).to_bytes(32, "big"))
    assert [entry.block_number for entry in index.logs(LogFilter(0, 9))] == [1]


def test_a_query_matching_too_many_logs_is_refused(index: EventIndex) -> None:
    entries = [registered(1, "0x" + f"{i:040x}") for i in range(MAX_LOG_RESULTS + 1)]
    entries = [
        LogEntry(e.block_number, e.block_hash, e.tx_hash, 0, i, e.address, e.topics, e.data)
        for i, e in enumerate(entries)
    ]
    index.add_block(1, bytes(32), entries)
    with pytest.raises(IndexLimitError):
        index.logs(LogFilter(0, 1))


def many_logs(block: int, count: int, fourth_topic: bytes) -> list[LogEntry]:
    """``count`` logs of one block, each with four topics, the last ``fourth_topic``."""
    topics = (bytes(32), bytes(32), bytes(32), fourth_topic)
    return [
        LogEntry(block, bytes(32), bytes(32), 0, i, bytes(20), topics, b"") for i in range(count)
    ]


def test_a_query_past_its_time_is_refused_and_one_on_any_topic_reads_only_its_answer(
    index: EventIndex, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With no time at all, a query that reads 20,000 logs is stopped, while one on the fourth
    topic alone is answered from its index: that position had none, and such a query read every
    log in its range (0.3 s over 500,000) while the block being mined waited for its lock."""
    rare = b"\x01" * 32
    index.add_block(1, bytes(32), many_logs(1, 20_000, bytes(32)))
    index.add_block(2, bytes(32), [many_logs(2, 1, rare)[0]])
    monkeypatch.setattr(index_module, "LOG_QUERY_BUDGET_S", 0.0)
    with pytest.raises(IndexLimitError, match="query timeout exceeded"):
        index.logs(LogFilter(1, 1))
    found = index.logs(LogFilter(0, 2, (), (None, None, None, (rare,))))
    assert [(entry.block_number, entry.topics[3]) for entry in found] == [(2, rare)]
    monkeypatch.setattr(index_module, "LOG_QUERY_BUDGET_S", 60.0)
    assert len(index.logs(LogFilter(1, 1))) == 20_000
    assert index.cursor() == (2, bytes(32))


def anchored(block: int, epoch: int, record_count: int, position: int = 0) -> LogEntry:
    return log(
        "Anchored",
        block,
        at=ANCHOR_LOG,
        position=position,
        abi=ANCHOR_ABI,
        node=ROBOT,
        epoch=epoch,
        root=b"\x01" * 32,
        recordCount=record_count,
        timestamp=block,
    )


def test_anchors_hold_every_uint64_epoch_and_count_in_order(index: EventIndex) -> None:
    """Epoch 2^63 failed the block with OverflowError, and every block after it."""
    epochs = [0, 5, 2**63 - 1, 2**63, UINT64_MAX]
    for block, epoch in enumerate(epochs, start=1):
        index.add_block(block, bytes(32), [anchored(block, epoch, UINT64_MAX - block)])
    index.add_block(len(epochs) + 1, bytes(32), [registered(len(epochs) + 1)])
    assert index.cursor() == (len(epochs) + 1, bytes(32))
    assert index.robot(ROBOT) is not None
    rows = index.anchors(ROBOT, None, 100)
    assert [(row["epoch"], row["record_count"]) for row in rows] == [
        (epoch, UINT64_MAX - block) for block, epoch in enumerate(epochs, start=1)
    ]
    for epoch in epochs:
        assert [row["epoch"] for row in index.anchors(None, epoch, 100)] == [epoch]
    assert index.anchors(None, 7, 100) == []
    assert index.advertisements(None, None, UINT64_MAX, 100) == []


def test_an_event_that_cannot_be_projected_still_indexes_its_block(
    index: EventIndex, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A projection that fails is undone and logged; the block, its logs and every later
    block are indexed (a failing block used to stop the index for good)."""

    def failing(db: sqlite3.Connection, *_: Any) -> None:
        db.execute("INSERT INTO robots VALUES ('half-done', x'00', 1, 1, 1, 0)")
        raise OverflowError("Python int too large to convert to SQLite INTEGER")

    monkeypatch.setitem(index_module._HANDLERS, "Anchored", failing)
    index.add_block(1, bytes(32), [anchored(1, 1, 1), registered(1, position=1)])
    index.add_block(2, (2).to_bytes(32, "big"), [anchored(2, 2, 2)])
    assert index.cursor() == (2, (2).to_bytes(32, "big"))
    assert len(index.logs(LogFilter(0, 2))) == 3
    assert index.robot(ROBOT) is not None
    assert index.robot("half-done") is None
    assert index.anchors(None, None, 100) == []


@pytest.mark.parametrize("event", ["RobotRegistered", "Advertised", "Anchored"])
def test_an_event_time_past_2_63_is_left_out_naming_it(
    index: EventIndex, caplog: pytest.LogCaptureFixture, event: str
) -> None:
    """An event's uint64 time went into SQLite as it was: past 2^63 - 1 the projection
    failed with OverflowError, which said nothing of which value. Such a time is no honest
    clock's, but a chain's all the same (a node can set its next block's time), so the event
    is left out, named, and its block indexed."""
    time = 2**63
    events = {
        "RobotRegistered": log(
            "RobotRegistered", 1, robot=ROBOT, metadataCid=METADATA, timestamp=time
        ),
        "Advertised": log(
            "Advertised",
            1,
            cidHash=bytes(32),
            advertiser=ROBOT,
            cid=METADATA,
            descriptionCid=b"",
            first=True,
            timestamp=time,
        ),
        "Anchored": log(
            "Anchored",
            1,
            at=ANCHOR_LOG,
            abi=ANCHOR_ABI,
            node=ROBOT,
            epoch=1,
            root=bytes(32),
            recordCount=1,
            timestamp=time,
        ),
    }
    with caplog.at_level(logging.ERROR, "robocloud.ledger.index"):
        index.add_block(1, bytes(32), [events[event]])
    (record,) = caplog.records
    assert record.exc_info is not None
    assert f"{event} timestamp 9223372036854775808 is past 2^63 - 1" in str(record.exc_info[1])
    assert index.cursor() == (1, bytes(32))
    assert len(index.logs(LogFilter(0, 1))) == 1
    assert index.robot(ROBOT) is None
    assert index.advertisements(None, None, 0, 10) == index.anchors(None, None, 10) == []
    index.add_block(2, bytes(32), [registered(2)])
    assert index.robot(ROBOT) is not None


def test_an_index_of_the_first_schema_is_migrated_in_place(tmp_path: Path) -> None:
    """An index written before epochs were biased keeps its rows and its cursor, and takes
    the anchors it could not store before."""
    path = tmp_path / "index.sqlite"
    old = sqlite3.connect(path)
    old.executescript(SCHEMA)
    old.execute(
        "INSERT INTO anchors VALUES (?, ?, ?, ?, ?, ?, ?)",
        (ROBOT, 2**63 - 1, b"\x01" * 32, 7, 1, 1, bytes(32)),
    )
    old.execute("INSERT INTO cursor VALUES (0, 1, ?)", (bytes(32),))
    old.commit()
    old.close()
    index = EventIndex(path, REGISTRY, ANCHOR_LOG)
    try:
        assert index.cursor() == (1, bytes(32))
        index.add_block(2, bytes(32), [anchored(2, 2**63, 8)])
        rows = index.anchors(ROBOT, None, 100)
        assert [(row["epoch"], row["record_count"]) for row in rows] == [(2**63 - 1, 7), (2**63, 8)]
    finally:
        index.close()
    reopened = EventIndex(path, REGISTRY, ANCHOR_LOG)
    try:
        assert [row["epoch"] for row in reopened.anchors(ROBOT, None, 100)] == [2**63 - 1, 2**63]
    finally:
        reopened.close()


def test_a_page_holds_whole_blocks_and_a_block_past_the_limit_alone(
    index: EventIndex, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(index_module, "MAX_LOG_RESULTS", 3)
    sizes = {1: 2, 2: 1, 3: 5, 5: 1}
    for block, size in sizes.items():
        index.add_block(block, bytes(32), [registered(block, position=i) for i in range(size)])

    def blocks(page: list[LogEntry]) -> list[int]:
        return [entry.block_number for entry in page]

    found, last = index.logs_page(LogFilter(0, 9))
    assert (blocks(found), last) == ([1, 1, 2], 2)
    found, last = index.logs_page(LogFilter(3, 9))
    assert (blocks(found), last) == ([3] * 5, 3)
    found, last = index.logs_page(LogFilter(4, 9))
    assert (blocks(found), last) == ([5], 9)
    assert len(index.logs(LogFilter(3, 3))) == 5
    with pytest.raises(IndexLimitError):
        index.logs(LogFilter(2, 3))


@pytest.mark.parametrize("where", ["", "WHERE node = ?"])
def test_anchors_are_read_in_chain_order_by_an_index_not_a_sort(
    index: EventIndex, where: str
) -> None:
    """Storage nodes anchor every few seconds; an unfiltered ``GET /v1/anchors`` scanned and
    sorted every anchor ever made (135 ms at a million), on the event loop."""
    sql = f"EXPLAIN QUERY PLAN SELECT * FROM anchors {where} ORDER BY block_number, node LIMIT 5"
    plan = " ".join(
        str(row[-1]) for row in index._db.execute(sql, ["0x" + "ab" * 20] if where else [])
    )
    assert "TEMP B-TREE" not in plan
    assert "anchors_block" in plan or "anchors_node_block" in plan


def advertised(block: int, position: int) -> LogEntry:
    cid = bytes.fromhex("01551220") + block.to_bytes(16, "big") + position.to_bytes(16, "big")
    return log(
        "Advertised",
        block,
        position=position,
        cidHash=cid[4:],
        advertiser=ROBOT,
        cid=cid,
        descriptionCid=METADATA,
        first=True,
        timestamp=block,
    )


def test_advertisements_are_read_on_from_a_position_past_a_block_fuller_than_a_page(
    index: EventIndex,
) -> None:
    """Read from a block number alone, a block of more advertisements than a page gave its
    first page again and again: a reader could never get past it."""
    index.add_block(3, bytes(32), [advertised(3, position) for position in range(5)])
    index.add_block(4, bytes(32), [advertised(4, 0)])
    read, since, after = [], 0, None
    for _ in range(4):
        page = index.advertisements(None, None, since, 2, after)
        read += [(row["block_number"], row["log_index"]) for row in page]
        if page:
            since, after = page[-1]["block_number"], page[-1]["log_index"]
    assert read == [(3, 0), (3, 1), (3, 2), (3, 3), (3, 4), (4, 0)]
    assert [row["log_index"] for row in index.advertisements(None, None, 3, 10, 3)] == [4, 0]
    assert index.advertisements(None, None, 4, 10, UINT64_MAX) == []
    assert index.advertisements(None, None, UINT64_MAX, 10, UINT64_MAX) == []
