"""``robocloud templates ...`` and ``robocloud query`` against a real storage service."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from robocloud.cli import app
from robocloud.identity import Identity
from robocloud.storage import Storage
from tests.conftest import ServiceFactory

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
