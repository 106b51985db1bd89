"""A new storage node in a deployment like ``make up``'s: cas takes writes only from registered
robots, and the ledger grants the node its role once it finds the node registered.

The node registered only before its first anchor. Until then cas refused its writes, so the
dataset of the first bag ingested on a fresh deployment was never published (its bag could not
go to cas), and the ledger's granter asked the idle node for its address every poll interval.
"""

from __future__ import annotations

from pathlib import Path

import httpx

from robocloud.cid import parse_cid
from robocloud.identity import Identity
from robocloud.ingest import Ingest
from robocloud.ledger import Ledger
from tests.conftest import ServiceFactory
from tests.integration.services.storage.ledger_proxy import upload_imu_bag
from tests.integration.services.storage.test_anchoring import node_state
from tests.procs import ServiceProcess, free_port
from tests.waiting import wait_for


def registered_only_cas(service_factory: ServiceFactory, ledger: ServiceProcess) -> ServiceProcess:
    return service_factory(
        "cas", {"ROBOCLOUD_AUTH": "registered", "ROBOCLOUD_LEDGER_URL": ledger.url}
    )


def test_an_idle_node_registers_at_start_and_is_granted_its_role(
    service_factory: ServiceFactory,
) -> None:
    """Nothing is written: the node still registers, and the ledger's granter finds it."""
    storage_port = free_port()
    ledger = service_factory(
        "ledger",
        {
            "ROBOCLOUD_STORAGE_URL": f"http://127.0.0.1:{storage_port}",
            "ROBOCLOUD_LEDGER_POLL_INTERVAL_S": "0.2",
        },
    )
    storage = service_factory(
        "storage",
        {
            "ROBOCLOUD_LEDGER_URL": ledger.url,
            "ROBOCLOUD_CAS_URL": registered_only_cas(service_factory, ledger).url,
            "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
            "ROBOCLOUD_STORAGE_ANCHOR_RETRY_S": "0.2",
        },
        port=storage_port,
    )
    state = wait_for(
        lambda: (s := node_state(storage))["standing"] == "anchoring" and s,
        "the idle node to register and be granted the storage_node role",
        timeout_s=60,
    )
    assert (state["last_epoch"], state["anchor_error"]) == (0, None)
    with Ledger.connect(ledger.url) as chain:
        assert chain.robot(state["address"]).registered
    granter_lines = ledger.log().count('"msg": "role granted"')
    assert granter_lines == 1, ledger.log()


def test_the_first_dataset_is_published_where_cas_takes_only_registered_robots(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """Anchoring off, so nothing registered the node before its first job: the publisher
    registers it before its first write to cas, which refused the bag with 403."""
    ledger = service_factory("ledger")
    cas = registered_only_cas(service_factory, ledger)
    storage = service_factory(
        "storage",
        {
            "ROBOCLOUD_LEDGER_URL": ledger.url,
            "ROBOCLOUD_CAS_URL": cas.url,
            "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
            "ROBOCLOUD_STORAGE_ANCHOR": "false",
        },
    )
    node = str(node_state(storage)["address"])
    with Ledger.connect(ledger.url) as chain:
        assert not chain.robot(node).registered

    _, job_id = upload_imu_bag(storage, identity, tmp_path / "run.bag")
    with Ingest(storage.url, identity) as ingest:
        done = ingest.wait(job_id, timeout_s=120)

    assert done["status"] == "succeeded", done["error"]
    dataset = done["dataset"]
    assert "error" not in dataset, dataset
    bag = parse_cid(dataset["cid"], "bag")
    with Ledger.connect(ledger.url) as chain:
        assert chain.robot(node).registered
        advertised = chain.advertisements(cid=bag.binary, advertiser=node)
    assert [event.tx_hash for event in advertised] == [dataset["tx"]]
    stored = httpx.get(f"{cas.url}/ipfs/{bag}", timeout=30)
    assert stored.content == (tmp_path / "run.bag").read_bytes()
