"""AnchorLog: only active storage nodes anchor, epochs strictly increase per node, reads."""

from __future__ import annotations

import pytest
from eth_tester.exceptions import TransactionFailed
from web3 import Web3

from tests.unit.contracts.chain import Chain, deploy

ROOT_1 = bytes.fromhex("11" * 32)
ROOT_2 = bytes.fromhex("22" * 32)
NOT_STORAGE = "AnchorLog: caller is not an active storage node"


def anchor_at(chain: Chain, node: str, epoch: int) -> list[object]:
    result: list[object] = chain.anchor_log.functions.anchorAt(node, epoch).call()
    return result


def test_constructor_binds_registry_and_role(chain: Chain) -> None:
    functions = chain.anchor_log.functions
    assert functions.registry().call() == chain.registry.address
    assert functions.storageNodeRole().call() == Web3.keccak(text="robocloud.role.storage_node")


def test_constructor_rejects_a_registry_that_is_not_a_contract(chain: Chain) -> None:
    with pytest.raises(TransactionFailed, match="AnchorLog: registry is not a contract"):
        deploy(chain.w3, "AnchorLog", chain.admin, chain.other)


def test_anchor_records_and_emits(chain: Chain, storage_node: str) -> None:
    receipt = chain.send(chain.anchor_log.functions.anchor(0, ROOT_1, 7), storage_node)
    ts = chain.timestamp(receipt)
    assert anchor_at(chain, storage_node, 0) == [ROOT_1, 7, ts, receipt["blockNumber"]]
    assert chain.anchor_log.functions.rootAt(storage_node, 0).call() == ROOT_1
    assert chain.anchor_log.functions.latest(storage_node).call() == [0, ROOT_1, 7, ts]
    assert chain.anchor_log.functions.anchorCount(storage_node).call() == 1
    assert chain.events(chain.anchor_log, "Anchored", receipt) == [
        {"node": storage_node, "epoch": 0, "root": ROOT_1, "recordCount": 7, "timestamp": ts}
    ]


def test_epochs_may_skip_and_every_root_stays_readable(chain: Chain, storage_node: str) -> None:
    chain.send(chain.anchor_log.functions.anchor(3, ROOT_1, 1), storage_node)
    second = chain.send(chain.anchor_log.functions.anchor(10, ROOT_2, 2), storage_node)
    assert chain.anchor_log.functions.rootAt(storage_node, 3).call() == ROOT_1
    assert chain.anchor_log.functions.rootAt(storage_node, 10).call() == ROOT_2
    assert chain.anchor_log.functions.rootAt(storage_node, 5).call() == bytes(32)
    assert chain.anchor_log.functions.latest(storage_node).call() == [
        10,
        ROOT_2,
        2,
        chain.timestamp(second),
    ]
    assert chain.anchor_log.functions.anchorCount(storage_node).call() == 2


def test_epochs_are_per_node(chain: Chain, storage_node: str) -> None:
    second_node = chain.other
    chain.send(chain.registry.functions.register(b"\x01second"), second_node)
    role = chain.registry.functions.STORAGE_NODE().call()
    chain.send(chain.registry.functions.grantRole(second_node, role), chain.admin)
    chain.send(chain.anchor_log.functions.anchor(5, ROOT_1, 1), storage_node)
    chain.send(chain.anchor_log.functions.anchor(1, ROOT_2, 1), second_node)
    assert chain.anchor_log.functions.rootAt(storage_node, 5).call() == ROOT_1
    assert chain.anchor_log.functions.rootAt(second_node, 1).call() == ROOT_2
    assert chain.anchor_log.functions.rootAt(storage_node, 1).call() == bytes(32)


@pytest.mark.parametrize("epoch", [4, 5])
def test_non_increasing_epoch_is_rejected(chain: Chain, storage_node: str, epoch: int) -> None:
    chain.send(chain.anchor_log.functions.anchor(5, ROOT_1, 1), storage_node)
    chain.assert_reverts(
        chain.anchor_log.functions.anchor(epoch, ROOT_2, 9),
        storage_node,
        "AnchorLog: epoch not increasing",
    )
    assert chain.anchor_log.functions.rootAt(storage_node, 5).call() == ROOT_1
    assert chain.anchor_log.functions.rootAt(storage_node, 4).call() == bytes(32)
    assert chain.anchor_log.functions.anchorCount(storage_node).call() == 1


def test_empty_root_is_rejected(chain: Chain, storage_node: str) -> None:
    chain.assert_reverts(
        chain.anchor_log.functions.anchor(1, bytes(32), 1), storage_node, "AnchorLog: empty root"
    )
    assert chain.anchor_log.functions.anchorCount(storage_node).call() == 0


def test_unregistered_account_cannot_anchor(chain: Chain) -> None:
    chain.assert_reverts(chain.anchor_log.functions.anchor(1, ROOT_1, 1), chain.other, NOT_STORAGE)
    assert anchor_at(chain, chain.other, 1) == [bytes(32), 0, 0, 0]


def test_registered_robot_without_the_role_cannot_anchor(chain: Chain) -> None:
    chain.send(chain.registry.functions.register(b"\x01robot"), chain.robot)
    reviewer = chain.registry.functions.REVIEWER().call()
    chain.send(chain.registry.functions.grantRole(chain.robot, reviewer), chain.admin)
    chain.assert_reverts(chain.anchor_log.functions.anchor(1, ROOT_1, 1), chain.robot, NOT_STORAGE)
    assert chain.anchor_log.functions.rootAt(chain.robot, 1).call() == bytes(32)


@pytest.mark.parametrize("how", ["deactivated", "suspended", "revoked"])
def test_storage_node_that_lost_its_standing_cannot_anchor(
    chain: Chain, storage_node: str, how: str
) -> None:
    registry = chain.registry.functions
    if how == "deactivated":
        chain.send(registry.deactivate(), storage_node)
    elif how == "suspended":
        chain.send(registry.setSuspended(storage_node, True), chain.admin)
    else:
        chain.send(registry.revokeRole(storage_node, registry.STORAGE_NODE().call()), chain.admin)
    chain.assert_reverts(chain.anchor_log.functions.anchor(1, ROOT_1, 1), storage_node, NOT_STORAGE)
    assert chain.anchor_log.functions.anchorCount(storage_node).call() == 0


def test_latest_of_a_node_without_anchors_reverts(chain: Chain) -> None:
    with pytest.raises(TransactionFailed) as raised:
        chain.anchor_log.functions.latest(chain.other).call()
    assert str(raised.value) == "execution reverted: AnchorLog: node has no anchors"
