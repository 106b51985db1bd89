"""A storage node killed (SIGKILL) after its ``Registry.advertise`` transaction was mined but
before the job saved what it published: the resumed job advertises nothing more.

Real ledger, cas and storage processes; the storage node reaches the ledger through a
forwarding proxy that, on the advertise transaction, forwards it, waits until the ledger has
mined it and then kills the node before answering. What decides where the kill lands is the
transaction itself, never a timer.
"""

from __future__ import annotations

import json
from pathlib import Path

import httpx

from robocloud.cid import CID, parse_cid
from robocloud.identity import Identity
from robocloud.ingest import Ingest
from robocloud.ledger import Ledger
from robocloud.ledger.rpc import JsonRpcClient
from robocloud.storage import Storage as StorageClient
from tests.bagfactory import START_NS, write_bag
from tests.conftest import ServiceFactory
from tests.integration.services.storage.counter import write_counter_records
from tests.integration.services.storage.ledger_proxy import (
    ADVERTISE,
    LedgerProxy,
    sends,
    serving,
    storage_behind,
    upload_imu_bag,
)
from tests.integration.services.storage.test_anchoring import node_state
from tests.integration.services.storage.test_ingest_http import Storage, approve
from tests.procs import ServiceProcess
from tests.scripted_http import Exchange, Reply
from tests.waiting import wait_for


class KillOnAdvertise(LedgerProxy):
    """A proxy script: every request goes to the ledger; the first advertise transaction is
    sent and mined, then the storage node is killed and gets no answer."""

    def __init__(self, ledger: ServiceProcess) -> None:
        super().__init__(ledger)
        self.armed = True
        self.advertise_tx: str | None = None

    def __call__(self, exchange: Exchange) -> Reply:
        with self.lock:
            kill = self.armed and exchange.method == "POST" and sends(exchange.body, ADVERTISE)
            self.armed = self.armed and not kill
        answer = self.forward(exchange)
        if not kill:
            return self.answer(answer)
        tx_hash = str(answer.json()["result"])
        with JsonRpcClient(f"{self.ledger.url}/rpc", service="ledger") as rpc:
            wait_for(
                lambda: rpc.request("eth_getTransactionReceipt", [tx_hash]),
                "the ledger to mine the advertise transaction",
            )
        self.advertise_tx = tx_hash
        return self.kill_storage()


def test_kill_9_after_the_advertise_is_mined_advertises_the_dataset_once(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    ledger = service_factory("ledger")
    cas = service_factory("cas")
    proxy = KillOnAdvertise(ledger)
    with serving(proxy) as server:
        env = {"ROBOCLOUD_STORAGE_ANCHOR": "false"}
        storage = storage_behind(proxy, server.url, service_factory, cas, env)
        imu, job_id = upload_imu_bag(storage, identity, tmp_path / "run.bag")
        proxy.wait_killed("the storage node to send its advertise transaction")

        saved = json.loads((storage.data_dir / "ingest" / job_id / "job.json").read_bytes())
        assert (saved["publish_attempts"], saved["dataset"]) == (1, None), saved

        storage.start()
        with StorageClient(storage.url, identity) as records, Ingest(storage.url, identity) as ing:
            done = ing.wait(job_id, timeout_s=180)
            assert done["status"] == "succeeded", done["error"]
            page = records.query(template=imu, limit=1000)
        node = str(httpx.get(f"{storage.url}/v1/node", timeout=10).json()["address"])
    assert page.next is None

    dataset = done["dataset"]
    with Ledger.connect(ledger.url) as chain:
        advertised = chain.advertisements(cid=parse_cid(dataset["cid"], "bag").binary)
    assert [(event.advertiser, event.tx_hash) for event in advertised] == [
        (node, proxy.advertise_tx)
    ]
    assert dataset == {
        "cid": dataset["cid"],
        "description": str(CID.from_bytes(advertised[0].description_cid)),
        "tx": proxy.advertise_tx,
    }

    bound = sum(topic["messages"] for topic in done["topics"] if topic["template"] is not None)
    times = [stored.record["t"] for stored in page.records]
    assert done["records"]["committed"] == bound
    assert len(times) == len(set(times)) == bound


class KillBeforeSecondAdvertise(LedgerProxy):
    """A proxy script: every request goes to the ledger but the second advertise transaction,
    which is never sent: the storage node is killed instead and gets no answer."""

    def __init__(self, ledger: ServiceProcess) -> None:
        super().__init__(ledger)
        self.advertises = 0

    def __call__(self, exchange: Exchange) -> Reply:
        with self.lock:
            advertise = exchange.method == "POST" and sends(exchange.body, ADVERTISE)
            self.advertises += advertise
            kill = advertise and self.advertises == 2
        return self.kill_storage() if kill else self.answer(self.forward(exchange))


def test_a_resumed_job_does_not_take_an_advertisement_of_another_description_for_its_own(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """Two robots ingest one bag; the second job, killed before its advertise was sent,
    is resumed. Its records are in a later epoch, so its description differs from the first
    job's: the node's earlier advertisement of the bag is not this job's, and the resumed job
    reported it as its own, its own description never advertised. (The node is registered
    first: its anchorer and its first publish registering at once revert one another.)"""
    ledger = service_factory("ledger")
    cas = service_factory("cas")
    proxy = KillBeforeSecondAdvertise(ledger)
    with serving(proxy) as server:
        env = {"ROBOCLOUD_STORAGE_EPOCH_S": "0.2"}
        storage = storage_behind(proxy, server.url, service_factory, cas, env)
        write_counter_records(storage, Identity.generate(), 0, 5, name="counter")
        wait_for(lambda: node_state(storage)["standing"] == "registered", "the node registered")
        with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ing:
            imu = approve(client, "sensor_msgs/msg/Imu")
            ing.bind(imu, msgtype="sensor_msgs/msg/Imu")
            bag = write_bag(tmp_path / "a.bag", "ros1", 50, start_ns=START_NS)
            first = ing.wait(ing.upload(bag)["id"], timeout_s=120)
            assert first["status"] == "succeeded", first["error"]
        again = write_bag(tmp_path / "b.bag", "ros1", 50, start_ns=START_NS)
        with Ingest(storage.url, Identity.generate()) as other_robot:
            second_id: str = other_robot.upload(again)["id"]
        proxy.wait_killed("the storage node to send its second advertise")

        storage.start()
        with Ingest(storage.url, identity) as ing:
            second = ing.wait(second_id, timeout_s=180)
        assert second["status"] == "succeeded", second["error"]
        node = str(httpx.get(f"{storage.url}/v1/node", timeout=10).json()["address"])

    assert first["dataset"]["cid"] == second["dataset"]["cid"]
    assert first["dataset"]["description"] != second["dataset"]["description"]
    with Ledger.connect(ledger.url) as chain:
        advertised = chain.advertisements(cid=parse_cid(first["dataset"]["cid"], "bag").binary)
    assert [
        (event.advertiser, event.tx_hash, str(CID.from_bytes(event.description_cid)))
        for event in advertised
    ] == [(node, done["dataset"]["tx"], done["dataset"]["description"]) for done in (first, second)]
