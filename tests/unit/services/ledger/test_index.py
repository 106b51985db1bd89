"""The event index in process, on a real SQLite file: fed logs, it answers as the chain would."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from eth_abi import encode
from eth_utils.address import to_checksum_address

from robocloud.ledger.abi import ContractAbi
from services.ledger.encoding import LogEntry
from services.ledger.index import MAX_LOG_RESULTS, EventIndex, IndexLimitError, LogFilter

REGISTRY = "0x" + "11" * 20
ANCHOR_LOG = "0x" + "22" * 20
IMPOSTOR = "0x" + "33" * 20
ROBOT = to_checksum_address("0x" + "ab" * 20)
METADATA = bytes.fromhex("01551220") + bytes(32)
ABI = ContractAbi.load("Registry")


@pytest.fixture
def index(tmp_path: Path) -> Iterator[EventIndex]:
    opened = EventIndex(tmp_path / "index.sqlite", REGISTRY, ANCHOR_LOG)
    yield opened
    opened.close()


def log(event: str, block: int, *, at: str = REGISTRY, position: int = 0, **args: Any) -> LogEntry:
    """An event log of the Registry ABI, encoded as the EVM emits it."""
    inputs = ABI.events[event]["inputs"]
    topics = [ABI.event_topic(event)]
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


def registered(block: int, robot: str = ROBOT, at: str = REGISTRY) -> LogEntry:
    return log("RobotRegistered", block, at=at, robot=robot, metadataCid=METADATA, timestamp=block)


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
