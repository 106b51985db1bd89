"""A storage node whose cas is out when a bag is ingested: the records are committed at once,
and the dataset is published once cas is back, by the node's own later attempt.

Before, that one failure left the dataset unpublished for good (no advertisement, no
description) and removed the bag, so nothing but ``robocloud describe`` by hand could
publish it.
"""

from __future__ import annotations

import re
from pathlib import Path

import httpx
from typer.testing import CliRunner

from robocloud.cid import parse_cid
from robocloud.cli import app
from robocloud.identity import Identity
from robocloud.ingest import Ingest
from robocloud.ledger import Ledger
from tests.conftest import ServiceFactory
from tests.integration.services.storage.ledger_proxy import upload_imu_bag
from tests.integration.services.storage.test_anchoring import node_state
from tests.procs import ServiceProcess, free_port
from tests.waiting import wait_for


def shown_job(storage: ServiceProcess, job_id: str) -> list[str]:
    """The lines ``robocloud job`` prints for the job."""
    shown = CliRunner().invoke(app, ["job", job_id, "--storage", storage.url])
    assert shown.exit_code == 0, shown.output
    return shown.stdout.splitlines()


def test_a_dataset_ingested_while_cas_is_out_is_published_once_cas_is_back(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    ledger = service_factory("ledger")
    cas_port = free_port()
    storage = service_factory(
        "storage",
        {
            "ROBOCLOUD_LEDGER_URL": ledger.url,
            "ROBOCLOUD_CAS_URL": f"http://127.0.0.1:{cas_port}",
            "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
            "ROBOCLOUD_STORAGE_ANCHOR": "false",
            "ROBOCLOUD_STORAGE_PUBLISH_RETRY_S": "1",
        },
    )
    _, job_id = upload_imu_bag(storage, identity, tmp_path / "run.bag")
    with Ingest(storage.url, identity) as ingest:
        done = ingest.wait(job_id, timeout_s=120)
        assert done["status"] == "succeeded", done["error"]
        assert done["records"]["committed"] > 0
        failed = done["dataset"]
        assert str(cas_port) in failed["error"], failed
        assert failed["attempts"] == 1
        assert failed["next_attempt_ns"] > done["updated_ns"] - 1
        job_dir = storage.data_dir / "ingest" / job_id
        assert sorted(path.name for path in job_dir.iterdir()) == ["bag.bag", "job.json"]
        retrying = shown_job(storage, job_id)[-1]
        assert retrying.startswith("dataset not published yet: "), retrying
        # A loaded machine may start the CLI after a later attempt (1 s, then 2 s) failed too.
        assert re.search(r"\(attempt [0-9]+; the node tries again in about ", retrying), retrying

        cas = service_factory("cas", port=cas_port)
        dataset = wait_for(
            lambda: "tx" in (d := ingest.job(job_id)["dataset"]) and d,
            "the dataset to be published once cas is back",
            timeout_s=120,
        )
    assert set(dataset) == {"cid", "description", "tx"}
    assert shown_job(storage, job_id)[-1] == (
        f"dataset {dataset['cid']}, described by {dataset['description']}, "
        f"advertised in {dataset['tx']}"
    )
    bag = parse_cid(dataset["cid"], "bag")
    node = str(node_state(storage)["address"])
    with Ledger.connect(ledger.url) as chain:
        advertised = chain.advertisements(cid=bag.binary, advertiser=node)
    assert [event.tx_hash for event in advertised] == [dataset["tx"]]
    stored = httpx.get(f"{cas.url}/ipfs/{bag}", timeout=30)
    assert stored.content == (tmp_path / "run.bag").read_bytes()
    wait_for(lambda: [p.name for p in job_dir.iterdir()] == ["job.json"], "the bag to go", 30)
    said = [line for line in storage.log().splitlines() if "dataset not published" in line]
    assert len(said) >= 1
    assert all('"retry": true' in line for line in said), said
