"""``robocloud templates ...``, ``query``, ``export`` and ``intervals`` against a real storage
service."""

from __future__ import annotations

import io
import json
from pathlib import Path

from mcap.reader import make_reader
from typer.testing import CliRunner

from robocloud.cli import app
from robocloud.identity import Identity
from robocloud.storage import Storage
from tests.bagfactory import write_bag
from tests.conftest import ServiceFactory
from tests.integration.services.storage.test_ingest_http import approved

runner = CliRunner()


def test_templates_and_query_from_the_cli(
    service_factory: ServiceFactory, identity: Identity, keystore: Path, tmp_path: Path
) -> None:
    storage = service_factory("storage")
    common = ["--storage", storage.url]
    signed = [*common, "--keystore", str(keystore)]
    template = tmp_path / "gps.json"
    template.write_text(json.dumps({"name": "gps", "fields": {"lat": "float", "fix": "string"}}))
    created = runner.invoke(app, ["templates", "create", str(template), *signed, "--json"])
    assert created.exit_code == 0, created.output
    assert json.loads(created.stdout)["status"] == "draft"
    bad = tmp_path / "bad.json"
    bad.write_text('{"name": "bad", "fields": {"a": "int", "a": "vec"}}')
    refused = runner.invoke(app, ["templates", "create", str(bad), *signed])
    assert refused.exit_code != 0
    assert "fields.a" in refused.stderr
    for step in (["submit", "gps@1"], ["review", "gps@1", "approve", "--reason", "fine"]):
        done = runner.invoke(app, ["templates", *step, *signed])
        assert done.exit_code == 0, done.output
    shown = runner.invoke(app, ["templates", "show", "gps@1", *common])
    assert "approved" in shown.stdout
    assert "fine" in shown.stdout
    listed = runner.invoke(app, ["templates", "list", *common, "--json"])
    assert json.loads(listed.stdout) == [
        {"id": "gps@1", "status": "approved", "author": identity.address}
    ]
    with Storage(storage.url, identity) as client:
        client.append(
            [
                {
                    "template": "gps@1",
                    "topic": "/fix",
                    "robot": identity.address,
                    "t": t,
                    "data": {"lat": t / 2, "fix": "rtk" if t % 2 else "none"},
                }
                for t in range(6)
            ]
        )
    table = runner.invoke(
        app, ["query", "--template", "gps@1", "--where", "lat>=1", *common, "--where", "fix=rtk"]
    )
    assert table.exit_code == 0, table.output
    assert [line.split()[0] for line in table.stdout.splitlines()[1:]] == ["gps-1-3", "gps-1-5"]
    as_json = runner.invoke(
        app, ["query", "--template", "gps@1", "--limit", "2", "--json", *common]
    )
    page = json.loads(as_json.stdout)
    assert [item["id"] for item in page["records"]] == ["gps-1-0", "gps-1-1"]
    assert page["next"] == "gps@1/1"
    wrong = runner.invoke(app, ["query", "--template", "gps@1", "--where", "alt>1", *common])
    assert wrong.exit_code != 0
    assert "unknown field" in wrong.stderr or "no field alt" in wrong.stderr


def test_a_bag_from_draft_to_verified_record_from_the_cli(
    service_factory: ServiceFactory, keystore: Path, tmp_path: Path
) -> None:
    """The README's flow: ingest, write the proposed drafts, create, submit, review, bind,
    ingest again, query; and the bag sent a third time, which stores nothing twice."""
    storage = service_factory("storage", {"ROBOCLOUD_STORAGE_PUBLISH_DATASETS": "false"})
    signed = ["--storage", storage.url, "--keystore", str(keystore)]
    bag = write_bag(tmp_path / "run.bag", "ros1", 60, start_ns=1_700_000_000_000_000_000)
    drafts = tmp_path / "drafts"
    first = runner.invoke(app, ["ingest", str(bag), "--drafts", str(drafts), *signed])
    assert first.exit_code == 0, first.output
    assert sorted(path.name for path in drafts.iterdir()) == [
        "image.json",
        "imu.json",
        "nav_sat_fix.json",
    ]
    steps = [
        ["templates", "create", str(drafts / "imu.json")],
        ["templates", "submit", "imu@1"],
        ["templates", "review", "imu@1", "approve"],
        ["bind", "imu@1", "--topic", "/imu"],
    ]
    for step in steps:
        done = runner.invoke(app, [*step, *signed])
        assert done.exit_code == 0, (step, done.output)
    second = runner.invoke(app, ["ingest", str(bag), *signed, "--json"])
    assert second.exit_code == 0, second.output
    job = json.loads(second.stdout)
    assert job["record_ids"] == {"imu@1": ["imu-1-0", "imu-1-47"]}
    both = runner.invoke(app, ["bind", "imu@1", "--topic", "/imu", "--msgtype", "x/msg/Y", *signed])
    assert both.exit_code == 2
    third = runner.invoke(app, ["ingest", str(bag), *signed])
    assert third.exit_code == 0, third.output
    said = third.stdout.splitlines()
    assert said[0].endswith(": succeeded, 0 records")
    assert (
        said[1]
        == f"  /imu (sensor_msgs/msg/Imu): ingested from this bag into imu@1 by job {job['id']}"
    )
    page = runner.invoke(app, ["query", "--template", "imu@1", "--storage", storage.url, "--json"])
    assert len(json.loads(page.stdout)["records"]) == 48


def test_export_and_intervals_from_the_cli(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """What a query selects, exported to MCAP (read back with the mcap library) and JSON
    lines, and a state's intervals; a refused export leaves no file, an existing one is kept
    without --force."""
    storage = service_factory("storage")
    common = ["--storage", storage.url]
    fixes = ["none", "rtk", "rtk", "none", "rtk", "none", "rtk"]
    with Storage(storage.url, identity) as client:
        gps = approved(client, {"name": "gps", "fields": {"lat": "float", "fix": "string"}})
        client.append(
            [
                {
                    "template": gps,
                    "topic": "/fix",
                    "robot": identity.address,
                    "t": t,
                    "data": {"lat": t / 2, "fix": fix},
                }
                for t, fix in enumerate(fixes)
            ]
        )
        selected = client.query(template=gps, where=["fix=rtk", "lat>=1"]).records
        expected_intervals = client.intervals(gps, "fix", "rtk")
    query = ["--template", gps, "--where", "fix=rtk", "--where", "lat>=1", *common]
    records = [stored.record for stored in selected]
    assert [record["t"] for record in records] == [2, 4, 6]

    mcap = tmp_path / "rtk.mcap"
    done = runner.invoke(app, ["export", str(mcap), *query, "--json"])
    assert done.exit_code == 0, done.output
    assert json.loads(done.stdout) == {
        "path": str(mcap),
        "format": "mcap",
        "size": mcap.stat().st_size,
    }
    reader = make_reader(io.BytesIO(mcap.read_bytes()))
    assert [json.loads(message.data) for _, _, message in reader.iter_messages()] == records

    lines = tmp_path / "rtk.jsonl"
    done = runner.invoke(app, ["export", str(lines), *query])
    assert done.exit_code == 0, done.output
    assert [json.loads(line) for line in lines.read_text().splitlines()] == records

    lines.write_text("kept\n")
    kept = runner.invoke(app, ["export", str(lines), *query])
    assert kept.exit_code == 1
    assert "exists" in kept.stderr
    assert "--force" in kept.stderr
    assert lines.read_text() == "kept\n"
    replaced = runner.invoke(app, ["export", str(lines), *query, "--force"])
    assert replaced.exit_code == 0, replaced.output
    assert lines.read_text().count("\n") == 3

    before = sorted(tmp_path.iterdir())
    unknown = runner.invoke(app, ["export", str(tmp_path / "rtk.txt"), *query])
    assert unknown.exit_code == 2
    assert "mcap or jsonl" in unknown.output
    refused = runner.invoke(app, ["export", str(tmp_path / "bad.mcap"), "--where", "alt>1", *query])
    assert refused.exit_code != 0
    assert "alt" in refused.stderr
    assert sorted(tmp_path.iterdir()) == before, "a refused export left a file behind"

    table = runner.invoke(
        app, ["intervals", "--template", gps, "--field", "fix", "--value", "rtk", *common]
    )
    assert table.exit_code == 0, table.output
    assert [line.split()[1:] for line in table.stdout.splitlines()[1:]] == [
        ["1", "3"],
        ["4", "5"],
        ["6", "still", "in"],
    ]
    as_json = runner.invoke(
        app, ["intervals", "--template", gps, "--field", "fix", "--value", "rtk", "--json", *common]
    )
    assert json.loads(as_json.stdout)["intervals"] == [
        interval.to_json() for interval in expected_intervals
    ]
