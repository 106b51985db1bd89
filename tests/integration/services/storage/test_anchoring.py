"""The storage node anchors its epochs on the ledger, in order, through an outage of the ledger."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from typer.testing import CliRunner

from robocloud import merkle
from robocloud.cas import Cas
from robocloud.cli import app
from robocloud.identity import Identity
from robocloud.ledger import JsonRpcClient, Ledger, LedgerService, Role
from robocloud.proofs import ProofVerificationError, verify_record_proof
from robocloud.storage import Storage
from robocloud.templates import canonical_record
from tests.conftest import ServiceFactory
from tests.integration.services.ledger.conftest import LEDGER_ENV, admin_of
from tests.integration.services.storage.counter import counter_record, write_counter_records
from tests.procs import ServiceProcess, free_port
from tests.waiting import wait_for


def node_state(storage: ServiceProcess) -> dict[str, Any]:
    return dict(httpx.get(f"{storage.url}/v1/node", timeout=10).json())


class Deployment:
    def __init__(self, factory: ServiceFactory, tmp: Path) -> None:
        storage_port = free_port()
        self.ledger = factory(
            "ledger",
            {
                "ROBOCLOUD_STORAGE_URL": f"http://127.0.0.1:{storage_port}",
                "ROBOCLOUD_LEDGER_POLL_INTERVAL_S": "0.2",
            },
        )
        self.cas = factory("cas")
        self.storage = factory(
            "storage",
            {
                "ROBOCLOUD_LEDGER_URL": self.ledger.url,
                "ROBOCLOUD_CAS_URL": self.cas.url,
                "ROBOCLOUD_STORAGE_EPOCH_S": "0.2",
                "ROBOCLOUD_STORAGE_ANCHOR_RETRY_S": "0.2",
            },
            port=storage_port,
        )
        with LedgerService(self.ledger.url) as service:
            self.anchor_log = service.contracts().anchor_log

    def proof(self, record_id: str) -> httpx.Response:
        return httpx.get(f"{self.storage.url}/v1/records/{record_id}/proof", timeout=10)

    def verify(self, record_id: str, body: Any | None = None) -> Any:
        with JsonRpcClient(f"{self.ledger.url}/rpc") as rpc:
            return verify_record_proof(
                self.proof(record_id).json() if body is None else body,
                rpc.request,
                anchor_log=self.anchor_log,
                record_id=record_id,
                chain_id=1337,
                node=node_state(self.storage)["address"],
            )


@pytest.fixture
def deployment(service_factory: ServiceFactory, tmp_path: Path) -> Deployment:
    return Deployment(service_factory, tmp_path)


def test_epochs_are_anchored_and_proofs_verify_on_chain(
    deployment: Deployment, identity: Identity
) -> None:
    storage = deployment.storage
    write_counter_records(storage, identity, 0, 300)
    state = wait_for(
        lambda: (s := node_state(storage))["last_anchored_epoch"] >= 1 and s, "epoch 1 anchored"
    )
    assert state["standing"] == "anchoring"
    with Ledger.connect(deployment.ledger.url) as ledger:
        assert ledger.has_role(state["address"], Role.STORAGE_NODE)
    proof = deployment.verify("imu-1-123")
    assert proof.record == counter_record(identity.address, 123)
    assert proof.tree_size == 300

    epoch = httpx.get(f"{storage.url}/v1/epochs/1", timeout=10).json()
    assert epoch["status"] == "anchored"
    assert epoch["heads"][0]["size"] == 300
    with Cas(deployment.cas.url) as cas:
        stored = json.loads(cas.get(epoch["manifest_cid"]))
    manifest_keys = ("epoch", "node", "heads", "record_count", "tmt_root")
    assert stored == {key: epoch[key] for key in manifest_keys}

    body = deployment.proof("imu-1-123").json()
    tampered = {**body, "record": {**body["record"], "data": {"i": 124}}}
    with pytest.raises(ProofVerificationError, match="not in its template log"):
        deployment.verify("imu-1-123", tampered)
    with pytest.raises(ProofVerificationError, match="asked for imu-1-5"):
        deployment.verify("imu-1-5", body)
    with (
        JsonRpcClient(f"{deployment.ledger.url}/rpc") as rpc,
        pytest.raises(ProofVerificationError, match="trusted one"),
    ):
        verify_record_proof(body, rpc.request, anchor_log="0x" + "11" * 20)


def test_a_robot_gets_a_verified_record_from_the_sdk_and_robocloud_verify(
    deployment: Deployment, identity: Identity
) -> None:
    """What ``robocloud verify`` checks, a robot has from ``Storage.verified_record``: the
    record, proved by the node and confirmed by the chain through the ledger's ``/rpc``."""
    write_counter_records(deployment.storage, identity, 0, 10)
    state = wait_for(
        lambda: (s := node_state(deployment.storage))["last_anchored_epoch"] >= 1 and s,
        "epoch 1 anchored",
    )
    with (
        Storage(deployment.storage.url) as storage,
        JsonRpcClient(f"{deployment.ledger.url}/rpc") as rpc,
    ):
        proof = storage.verified_record(
            "imu-1-7", rpc.request, anchor_log=deployment.anchor_log, node=state["address"]
        )
    assert proof.record == counter_record(identity.address, 7)
    assert (proof.anchor.chain_id, proof.anchor.node, proof.epoch) == (1337, state["address"], 1)

    urls = ["--storage", deployment.storage.url, "--ledger", deployment.ledger.url]
    result = CliRunner().invoke(app, ["verify", "imu-1-7", *urls, "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout) == {"id": "imu-1-7", "verified": True, **proof.to_json()}


def test_epochs_cut_while_the_ledger_is_down_are_anchored_in_order_when_it_returns(
    deployment: Deployment, identity: Identity
) -> None:
    storage, ledger = deployment.storage, deployment.ledger
    write_counter_records(storage, identity, 0, 10)
    wait_for(lambda: node_state(storage)["last_anchored_epoch"] == 1, "epoch 1 anchored")
    ledger.stop()
    write_counter_records(storage, identity, 10, 20)
    wait_for(lambda: node_state(storage)["last_epoch"] == 2, "epoch 2 cut")
    write_counter_records(storage, identity, 0, 5, "gps")
    state = wait_for(
        lambda: (s := node_state(storage))["last_epoch"] == 3 and s["anchor_error"] and s,
        "epoch 3 cut, anchoring failing",
    )
    assert state["last_anchored_epoch"] == 1
    waiting = deployment.proof("imu-1-15")
    assert waiting.status_code == 409
    assert waiting.json()["error"]["code"] == "not_anchored"
    assert waiting.json()["error"]["details"] == {"id": "imu-1-15", "epoch": 2}
    assert deployment.proof("gps-1-4").json()["error"]["details"]["epoch"] == 3

    ledger.start()
    wait_for(lambda: node_state(storage)["last_anchored_epoch"] == 3, "epochs 2 and 3 anchored")
    node = node_state(storage)["address"]
    with Ledger.connect(ledger.url) as client:
        anchored = client.anchors(node=node)
        assert [anchor.epoch for anchor in anchored] == [1, 2, 3]
        assert [anchor.record_count for anchor in anchored] == [10, 20, 25]
    assert deployment.verify("imu-1-15").epoch == 2
    assert deployment.verify("gps-1-4").epoch == 3
    assert deployment.verify("imu-1-3").epoch == 1
    epoch_2 = httpx.get(f"{storage.url}/v1/epochs/2", timeout=10).json()
    root = bytes.fromhex(epoch_2["heads"][0]["root"])
    leaves = [
        merkle.leaf_hash(canonical_record(counter_record(identity.address, i))) for i in range(20)
    ]
    assert root == merkle.root(leaves)


def test_a_node_waiting_for_its_role_anchors_once_granted_and_says_so_once(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    ledger = service_factory("ledger", LEDGER_ENV)  # no storage URL: nothing grants the role
    storage = service_factory(
        "storage",
        {
            "ROBOCLOUD_LEDGER_URL": ledger.url,
            "ROBOCLOUD_CAS_URL": service_factory("cas").url,
            "ROBOCLOUD_STORAGE_EPOCH_S": "0.2",
            "ROBOCLOUD_STORAGE_ANCHOR_RETRY_S": "0.1",
        },
    )
    write_counter_records(storage, identity, 0, 10)
    refused = wait_for(
        lambda: (s := node_state(storage))["standing"] == "registered" and s, "the node registered"
    )
    assert "lacks the storage_node role" in refused["anchor_error"]
    assert refused["last_anchored_epoch"] == 0
    time.sleep(1)  # ten more refused attempts at the base interval
    assert said(storage, "waiting for the storage_node role") == 1, storage.log()
    assert said(storage, "anchoring failed; retrying") == 0, storage.log()

    with Ledger.connect(ledger.url, admin_of(ledger)) as admin:
        admin.grant_role(refused["address"], Role.STORAGE_NODE)
    state = wait_for(
        lambda: (s := node_state(storage))["last_anchored_epoch"] == 1 and s, "epoch 1 anchored"
    )
    assert state["standing"] == "anchoring"
    assert state["anchor_error"] is None


def said(storage: ServiceProcess, message: str) -> int:
    """How many log lines say ``message``: the anchorer says each distinct error once, not
    once per attempt."""
    lines = [json.loads(line) for line in storage.log().splitlines() if line.startswith("{")]
    return sum(line.get("msg") == message for line in lines)
