"""robocloud.ledger against a real node (anvil): transactions signed by the robot's own key."""

from __future__ import annotations

from dataclasses import replace

import pytest

from robocloud.errors import MissingIdentityError
from robocloud.ledger import Ledger, RevertError, Role, RpcError
from robocloud.ledger.transactions import quantity
from tests.integration.robocloud.ledger.conftest import Deployment, LedgerFactory
from tests.integration.robocloud.ledger.nodes import CHAIN_ID, robot_ledger

METADATA = bytes.fromhex("01701220") + bytes(range(32))
CID = bytes.fromhex("01551220") + bytes(range(1, 33))
DESCRIPTION = bytes.fromhex("01711220") + bytes(range(2, 34))


def nonce(ledger: Ledger) -> int:
    assert ledger.identity is not None
    return quantity(
        ledger.rpc.request("eth_getTransactionCount", [ledger.identity.address, "latest"])
    )


def test_register_and_read_back(new_robot: LedgerFactory) -> None:
    robot = new_robot()
    receipt = robot.register(METADATA)
    assert receipt.status == 1
    assert robot.chain_id == CHAIN_ID
    assert robot.identity is not None
    record = robot.robot(robot.identity.address)
    assert (record.metadata_cid, record.registered, record.is_active) == (METADATA, True, True)
    block = robot.rpc.request("eth_getBlockByNumber", [hex(receipt.block_number), False])
    assert record.registered_at == quantity(block["timestamp"])
    assert robot.is_active(robot.identity.address)


def test_a_revert_found_by_estimation_sends_nothing(new_robot: LedgerFactory) -> None:
    robot = new_robot()
    robot.register(METADATA)
    before = nonce(robot)
    with pytest.raises(RevertError) as raised:
        robot.register(METADATA)
    assert raised.value.reason == "Registry: already registered"
    assert raised.value.tx_hash is None
    assert nonce(robot) == before


def test_a_mined_revert_carries_its_decoded_reason(
    deployment: Deployment, new_robot: LedgerFactory
) -> None:
    robot = new_robot()
    assert robot._transactor is not None
    data = robot.registry.encode_call("advertise", CID, b"")
    with pytest.raises(RevertError) as raised:
        robot._transactor.send(deployment.addresses.registry, data, gas=200_000)
    assert raised.value.reason == "Registry: advertiser is not an active robot"
    assert raised.value.tx_hash is not None
    receipt = robot.rpc.request("eth_getTransactionReceipt", [raised.value.tx_hash])
    assert quantity(receipt["status"]) == 0
    assert robot.advertisement(CID) is None


def test_advertise_keeps_the_first_advertiser(new_robot: LedgerFactory) -> None:
    first, second = new_robot(), new_robot()
    first.register(METADATA)
    second.register(METADATA)
    cid = CID[:-1] + b"\x99"
    one = first.advertise(cid, DESCRIPTION)
    two = second.advertise(cid)
    assert first.identity is not None
    assert second.identity is not None
    assert (one.first, one.advertiser, one.description_cid) == (
        True,
        first.identity.address,
        DESCRIPTION,
    )
    assert (two.first, two.advertiser, two.description_cid) == (False, second.identity.address, b"")
    summary = first.advertisement(cid)
    assert summary is not None
    assert (summary.first_advertiser, summary.count) == (first.identity.address, 2)
    assert (summary.first_timestamp, summary.first_block) == (one.timestamp, one.block_number)
    assert summary.description_cid == DESCRIPTION
    assert first.advertisements(cid=cid) == [one, two]
    assert first.advertisements(cid=cid, advertiser=second.identity.address) == [two]
    assert second.advertisements(advertiser=first.identity.address) == [one]


@pytest.mark.parametrize(
    ("cid", "description", "reason"),
    [
        (b"", b"", "Registry: empty CID"),
        (b"\x01" * 129, b"", "Registry: CID too long"),
        (CID, b"\x01" * 129, "Registry: CID too long"),
    ],
)
def test_advertise_rejects_bad_cids(
    new_robot: LedgerFactory, cid: bytes, description: bytes, reason: str
) -> None:
    robot = new_robot()
    robot.register(METADATA)
    before = nonce(robot)
    with pytest.raises(RevertError, match=reason):
        robot.advertise(cid, description)
    assert nonce(robot) == before
    assert robot.advertisement(cid) is None


def test_unregistered_robot_cannot_advertise(new_robot: LedgerFactory) -> None:
    robot = new_robot()
    with pytest.raises(RevertError) as raised:
        robot.advertise(CID + b"\x01")
    assert raised.value.reason == "Registry: advertiser is not an active robot"
    assert robot.advertisement(CID + b"\x01") is None


def test_storage_node_anchors_and_anyone_reads(
    deployment: Deployment, new_robot: LedgerFactory
) -> None:
    node = new_robot()
    node.register(METADATA)
    assert node.identity is not None
    address = node.identity.address
    assert node.latest_anchor(address) is None
    deployment.admin.grant_role(address, Role.STORAGE_NODE)
    assert node.has_role(address, Role.STORAGE_NODE)
    assert not node.has_role(address, Role.REVIEWER)
    first = node.anchor(1, b"\x11" * 32, 5)
    second = node.anchor(4, b"\x44" * 32, 9)
    reader = robot_ledger(deployment.url, deployment.addresses, None)
    assert reader.anchor_at(address, 1) == replace(first, tx_hash=None)
    assert reader.anchor_at(address, 2) is None
    latest = reader.latest_anchor(address)
    assert latest is not None
    assert (latest.epoch, latest.root, latest.record_count) == (4, b"\x44" * 32, 9)
    assert reader.anchors(node=address) == [first, second]
    assert reader.anchors(node=address, epoch=4) == [second]
    block = second.block_number
    assert reader.anchors(node=address, from_block=block, to_block=block) == [second]
    assert reader.anchors(node=address, to_block=first.block_number) == [first]
    reader.close()


def test_anchor_rejections(deployment: Deployment, new_robot: LedgerFactory) -> None:
    node, robot = new_robot(), new_robot()
    node.register(METADATA)
    robot.register(METADATA)
    assert node.identity is not None
    assert robot.identity is not None
    deployment.admin.grant_role(node.identity.address, Role.STORAGE_NODE)
    node.anchor(7, b"\x07" * 32, 1)
    with pytest.raises(RevertError) as raised:
        robot.anchor(1, b"\x01" * 32, 1)
    assert raised.value.reason == "AnchorLog: caller is not an active storage node"
    for epoch in (7, 6):
        with pytest.raises(RevertError) as raised:
            node.anchor(epoch, b"\x08" * 32, 1)
        assert raised.value.reason == "AnchorLog: epoch not increasing"
    assert node.anchor_at(node.identity.address, 7) is not None
    assert node.anchor_at(node.identity.address, 6) is None
    assert robot.anchors(node=robot.identity.address) == []


def test_admin_only_operations_revert_for_robots(new_robot: LedgerFactory) -> None:
    robot = new_robot()
    robot.register(METADATA)
    assert robot.identity is not None
    with pytest.raises(RevertError, match="Registry: caller is not the admin"):
        robot.grant_role(robot.identity.address, Role.STORAGE_NODE)
    assert not robot.has_role(robot.identity.address, Role.STORAGE_NODE, active=False)


def test_node_errors_surface_as_rpc_errors(new_robot: LedgerFactory) -> None:
    """What the node refuses is an ``RpcError`` naming the method (not a revert, not a crash)."""
    robot = new_robot()
    assert robot.identity is not None
    with pytest.raises(RpcError) as raised:
        robot.rpc.request("eth_sendRawTransaction", ["0x1234"])
    assert raised.value.method == "eth_sendRawTransaction"
    robot.register(METADATA)
    transaction = {"chainId": CHAIN_ID, "nonce": 0, "gas": 21_000, "gasPrice": 10**10}
    transaction |= {"to": robot.identity.address, "value": 1, "data": b""}
    stale = robot.identity.account.sign_transaction(transaction).raw_transaction
    with pytest.raises(RpcError, match="nonce"):
        robot.rpc.request("eth_sendRawTransaction", ["0x" + bytes(stale).hex()])
    assert nonce(robot) == 1


def test_unfunded_robot_gets_a_clear_error(new_robot: LedgerFactory) -> None:
    robot = new_robot(funded=False)
    with pytest.raises(RpcError, match=r"(?i)insufficient funds"):
        robot.register(METADATA)
    assert robot.identity is not None
    assert not robot.robot(robot.identity.address).registered


def test_writes_need_an_identity(deployment: Deployment) -> None:
    reader = robot_ledger(deployment.url, deployment.addresses, None)
    with pytest.raises(MissingIdentityError):
        reader.register(METADATA)
    reader.close()
