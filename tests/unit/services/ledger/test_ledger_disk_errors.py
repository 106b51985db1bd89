"""The embedded ledger after a disk error: the index catches up, the faucet gives a grant back."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from eth_abi import encode
from eth_account import Account
from eth_utils.crypto import keccak

from robocloud.ledger.models import RegistrationMode
from services.ledger import node
from services.ledger.calls import CallLimits
from services.ledger.faucet import FaucetLimits
from services.ledger.filters import Filters
from services.ledger.node import EmbeddedLedger
from services.ledger.pool import PoolLimits

METADATA = bytes.fromhex("01551220") + bytes(32)


@pytest.fixture
def ledger(tmp_path: Path) -> Iterator[EmbeddedLedger]:
    opened = EmbeddedLedger(
        tmp_path,
        "a passphrase for tests",
        FaucetLimits(tmp_path / "faucet.sqlite", 3600, 60),
        10**18,
        CallLimits(),
        PoolLimits(),
        RegistrationMode.OPEN,
        Filters(100, 300),
        25_000_000,
    )
    yield opened
    opened.close()


def rpc(ledger: EmbeddedLedger, method: str, *params: Any) -> Any:
    answer = ledger.dispatcher.answer(
        {"jsonrpc": "2.0", "id": 1, "method": method, "params": list(params)}
    )
    assert "result" in answer, answer
    return answer["result"]


def register(ledger: EmbeddedLedger, robot: Any) -> int:
    """``robot`` registers itself; the block that mined it."""
    call = keccak(b"register(bytes)")[:4] + encode(["bytes"], [METADATA])
    transaction = {
        "chainId": ledger.chain_id,
        "nonce": 0,
        "gas": 200_000,
        "gasPrice": 10**10,
        "to": ledger.deployment.registry,
        "data": call,
    }
    raw = bytes(robot.sign_transaction(transaction).raw_transaction)
    tx_hash = rpc(ledger, "eth_sendRawTransaction", "0x" + raw.hex())
    return int(rpc(ledger, "eth_getTransactionReceipt", tx_hash)["blockNumber"], 16)


def test_after_a_failed_index_write_the_index_catches_up_with_the_block_mined(
    ledger: EmbeddedLedger, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The catch-up after a failed index write stopped at the chain's head, which moves only
    after the index has its block: the index stayed one block behind for good, and a log
    filter passed over the blocks it lacked."""
    robots = [Account.create() for _ in range(3)]
    for robot in robots:
        ledger.fund(robot.address)
    registry_filter = rpc(ledger, "eth_newFilter", {"address": ledger.deployment.registry})
    add_block = ledger.index.add_block

    def full_disk_once(*args: Any) -> None:
        monkeypatch.setattr(ledger.index, "add_block", add_block)
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(ledger.index, "add_block", full_disk_once)
    mined = [register(ledger, robot) for robot in robots]
    assert ledger.index.cursor()[0] == ledger.chain.head().block_number == mined[-1]
    assert all(ledger.index.robot(robot.address) is not None for robot in robots)
    delivered = rpc(ledger, "eth_getFilterChanges", registry_filter)
    assert [int(log["blockNumber"], 16) for log in delivered] == mined


def test_a_log_filter_reports_no_further_than_the_index(
    ledger: EmbeddedLedger, monkeypatch: pytest.MonkeyPatch
) -> None:
    robot = Account.create()
    ledger.fund(robot.address)
    registry_filter = rpc(ledger, "eth_newFilter", {"address": ledger.deployment.registry})
    monkeypatch.setattr(ledger.index, "add_block", lambda *args: None)
    block = register(ledger, robot)
    assert rpc(ledger, "eth_getFilterChanges", registry_filter) == []
    monkeypatch.undo()
    ledger.catch_up()
    delivered = rpc(ledger, "eth_getFilterChanges", registry_filter)
    assert [int(log["blockNumber"], 16) for log in delivered] == [block]


def test_a_faucet_grant_a_disk_error_stopped_is_given_back(
    ledger: EmbeddedLedger, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Only a chain refusal gave the grant back: after a disk error the robot, never funded,
    was refused for an hour, across restarts."""
    robot = Account.create().address

    def disk_error(*args: Any, **kwargs: Any) -> None:
        raise sqlite3.OperationalError("disk I/O error")

    monkeypatch.setattr(node, "send_as", disk_error)
    with pytest.raises(sqlite3.OperationalError):
        ledger.fund(robot)
    monkeypatch.undo()
    funded = ledger.fund(robot)
    assert funded["address"] == robot
    assert int(rpc(ledger, "eth_getBalance", robot, "latest"), 16) == 10**18


def transfer(ledger: EmbeddedLedger, sender: Any, nonce: int) -> str:
    transaction = {
        "chainId": ledger.chain_id,
        "nonce": nonce,
        "gas": 21_000,
        "gasPrice": 10**10,
        "to": "0x" + "77" * 20,
        "value": 1,
    }
    raw = bytes(sender.sign_transaction(transaction).raw_transaction)
    return str(rpc(ledger, "eth_sendRawTransaction", "0x" + raw.hex()))


def test_a_disk_error_mining_a_waiting_transaction_fails_neither_it_nor_its_opener(
    ledger: EmbeddedLedger, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Nonce 1 waited; nonce 0 was mined and durable, then mining nonce 1 hit a disk error:
    nonce 0 was answered -32603 (its robot signed it again: "nonce too low") and nonce 1,
    taken from the pool, was lost."""
    robot = Account.create()
    ledger.fund(robot.address)
    waiting = transfer(ledger, robot, 1)
    chain = ledger.chain
    mine = chain._mine
    mined: list[bytes] = []

    def second_fails(transaction: Any, vm: Any) -> Any:
        if mined:
            raise sqlite3.OperationalError("disk I/O error")
        mined.append(transaction.hash)
        return mine(transaction, vm)

    monkeypatch.setattr(chain, "_mine", second_fails)
    opener = transfer(ledger, robot, 0)
    chain._promoter.submit(lambda: None).result()  # its one retry, failing too, is over
    assert rpc(ledger, "eth_getTransactionReceipt", opener)["status"] == "0x1"
    assert rpc(ledger, "eth_getTransactionReceipt", waiting) is None
    assert chain._pool.find(bytes.fromhex(waiting[2:])) is not None
    monkeypatch.undo()
    chain._promote(bytes.fromhex(robot.address[2:]))
    assert rpc(ledger, "eth_getTransactionReceipt", waiting)["status"] == "0x1"
