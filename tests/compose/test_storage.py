"""storage in Compose: a bag ingested through the published port, queried, and one of its
records verified against the chain with ``robocloud verify`` (the node got its role from the
ledger at start, with no manual step)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import httpx
import pytest
from typer.testing import CliRunner

from robocloud.cli import app
from robocloud.ingest import Ingest
from robocloud.storage import Storage
from tests.bagfactory import write_bag
from tests.compose.deployment import Deployment

pytestmark = pytest.mark.compose

START_NS = 1_700_000_000_000_000_000


def test_ingest_query_and_verify_against_the_chain(deployment: Deployment, tmp_path: Path) -> None:
    url = deployment.urls["storage"]
    bag = write_bag(tmp_path / "run.bag", "ros1", 100, start_ns=START_NS)
    with (
        Storage(url, deployment.identity, timeout=30) as records,
        Ingest(url, deployment.identity, timeout=30) as ingest,
    ):
        proposed = ingest.wait(ingest.upload(bag)["id"], timeout_s=120)
        draft = next(t["draft"] for t in proposed["topics"] if t["topic"] == "/imu")
        name = f"compose_imu_{time.time_ns()}"
        created = records.create_template({**draft, "name": name})
        records.submit_template(created.id)
        records.review_template(created.id, "approve", "compose test")
        ingest.bind(created.id, topic="/imu")
        job = ingest.wait(ingest.upload(bag)["id"], timeout_s=120)
        assert job["status"] == "succeeded", job["error"]
        committed = job["records"]["committed"]
        assert committed > 0
        page = records.query(template=created.id, start=START_NS, limit=1000)
    assert len(page.records) == committed
    assert page.records[0].record["t"] >= START_NS
    record_id = page.records[-1].id

    deadline = time.monotonic() + 60
    while httpx.get(f"{url}/v1/records/{record_id}/proof", timeout=10).status_code == 409:
        assert time.monotonic() < deadline, "the record's epoch was not anchored within 60 s"
        time.sleep(0.5)
    verified = CliRunner().invoke(
        app,
        ["verify", record_id, "--storage", url, "--ledger", deployment.urls["ledger"], "--json"],
    )
    assert verified.exit_code == 0, verified.output
    answer = json.loads(verified.stdout)
    assert answer["record"] == page.records[-1].record
