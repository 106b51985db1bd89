"""The SDK against the service: faucet, register, advertise, anchor; REST reads from the index."""

from __future__ import annotations

import httpx
import pytest

from robocloud.cid import CID
from robocloud.ledger import LedgerService, RevertError, Role
from tests.integration.services.ledger.conftest import METADATA, RobotFactory, Service, head

CID_TEXT = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"


def test_register_advertise_and_read_back(service: Service, robot: RobotFactory) -> None:
    first, second = robot(), robot()
    assert first.identity is not None
    assert second.identity is not None
    record = httpx.get(f"{service.url}/v1/robots/{first.identity.address.lower()}").json()
    assert record["address"] == first.identity.address
    assert record["metadata"]["hex"] == "0x" + METADATA.hex()
    assert (record["active"], record["roles"]) == (True, [])
    cid = CID.decode(CID_TEXT).binary
    one = first.advertise(cid)
    two = second.advertise(cid)
    assert (one.first, two.first) == (True, False)
    answer = httpx.get(f"{service.url}/v1/advertisements", params={"cid": CID_TEXT}).json()
    rows = answer["advertisements"]
    assert [(r["advertiser"], r["first"], r["cid"]) for r in rows] == [
        (first.identity.address, True, CID_TEXT),
        (second.identity.address, False, CID_TEXT),
    ]
    by_second = httpx.get(
        f"{service.url}/v1/advertisements",
        params={"advertiser": second.identity.address, "since": two.block_number},
    ).json()["advertisements"]
    assert [r["tx"] for r in by_second] == [two.tx_hash]
    assert first.advertisements(cid=cid) == [one, two]
    with LedgerService(service.url) as reader:
        from_one = reader.advertisements(since=one.block_number, cid=CID_TEXT)
        assert [ad.tx_hash for ad in from_one] == [one.tx_hash, two.tx_hash]
        past_one = reader.advertisements(
            since=one.block_number, after_log_index=from_one[0].log_index, cid=CID_TEXT
        )
    assert past_one == from_one[1:]


def test_storage_node_anchors(service: Service, robot: RobotFactory) -> None:
    node = robot()
    assert node.identity is not None
    address = node.identity.address
    service.admin.grant_role(address, Role.STORAGE_NODE)
    record = httpx.get(f"{service.url}/v1/robots/{address}").json()
    assert record["roles"] == ["storage_node"]
    anchored = node.anchor(3, b"\x33" * 32, 7)
    rows = httpx.get(f"{service.url}/v1/anchors", params={"node": address}).json()["anchors"]
    assert [(r["epoch"], r["root"], r["record_count"], r["tx"]) for r in rows] == [
        (3, "0x" + "33" * 32, 7, anchored.tx_hash)
    ]
    assert rows[0]["contract"] == service.admin.addresses.anchor_log
    assert node.anchors(node=address) == [anchored]


def test_anchor_from_a_non_storage_node_is_rejected(service: Service, robot: RobotFactory) -> None:
    plain = robot()
    assert plain.identity is not None
    before = head(service.url)
    with pytest.raises(RevertError) as raised:
        plain.anchor(1, b"\x01" * 32, 1)
    assert raised.value.reason == "AnchorLog: caller is not an active storage node"
    assert head(service.url) == before
    rows = httpx.get(f"{service.url}/v1/anchors", params={"node": plain.identity.address})
    assert rows.json() == {"anchors": []}


def test_non_increasing_epoch_is_rejected(service: Service, robot: RobotFactory) -> None:
    node = robot()
    assert node.identity is not None
    service.admin.grant_role(node.identity.address, Role.STORAGE_NODE)
    node.anchor(5, b"\x05" * 32, 1)
    before = head(service.url)
    for epoch in (5, 4):
        with pytest.raises(RevertError) as raised:
            node.anchor(epoch, b"\x06" * 32, 1)
        assert raised.value.reason == "AnchorLog: epoch not increasing"
    assert head(service.url) == before
    rows = httpx.get(f"{service.url}/v1/anchors", params={"node": node.identity.address}).json()
    assert [(r["epoch"], r["root"]) for r in rows["anchors"]] == [(5, "0x" + "05" * 32)]
