"""``robocloud register``, ``advertise`` and ``robot`` against a real ledger service."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import httpx
from typer.testing import CliRunner, Result

from robocloud.cid import CID
from robocloud.cli import app
from robocloud.identity import Identity
from tests.conftest import ServiceFactory
from tests.integration.services.ledger.conftest import Service
from tests.scripted_http import json_reply, nested_json, scripted_server

runner = CliRunner()
DATA_CID = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"
ADDRESS = "0x5B38Da6a701c568545dCfcB03FcB875f56beddC4"


def test_register_funds_registers_and_is_idempotent(
    service: Service, keystore: Path, identity: Identity
) -> None:
    path = keystore
    common = ["--keystore", str(path), "--ledger", service.url]
    first = runner.invoke(app, ["register", *common])
    assert first.exit_code == 0, first.output
    assert "from the faucet" in first.output
    assert f"{identity.address} registered" in first.output

    record = httpx.get(f"{service.url}/v1/robots/{identity.address}").json()
    did = f"did:pkh:eip155:1337:{identity.address}"
    assert record["active"] is True
    assert record["metadata"]["cid"] == str(CID.from_block(did.encode()))

    again = runner.invoke(app, ["register", *common])
    assert again.exit_code == 0, again.output
    assert "already registered" in again.output

    shown = runner.invoke(app, ["robot", identity.address, "--ledger", service.url])
    assert shown.exit_code == 0, shown.output
    assert "state      active" in shown.stdout
    registered_at = datetime.fromtimestamp(record["registered_at"], UTC)
    iso = registered_at.isoformat().replace("+00:00", "Z")
    assert f"registered {iso}" in shown.stdout
    assert f"metadata   {CID.from_block(did.encode())}" in shown.stdout

    as_json = runner.invoke(app, ["robot", "--json", *common])
    assert json.loads(as_json.stdout) == {
        "address": identity.address,
        "state": "active",
        "metadata": str(CID.from_block(did.encode())),
        "registered_at": iso,
    }


def test_register_prints_json(service: Service, keystore: Path, identity: Identity) -> None:
    path = keystore
    common = ["--keystore", str(path), "--ledger", service.url, "--json"]
    first = json.loads(runner.invoke(app, ["register", *common]).stdout)
    assert first["address"] == identity.address
    assert (first["registered"], first["new"], first["funded_wei"]) == (True, True, 10**18)
    assert first["tx"].startswith("0x")
    assert isinstance(first["block"], int)
    again = json.loads(runner.invoke(app, ["register", *common]).stdout)
    assert again == {
        "address": identity.address,
        "registered": True,
        "pending": False,
        "new": False,
    }


def test_advertise_records_the_first_advertiser(
    service: Service, keystore: Path, identity: Identity
) -> None:
    path = keystore
    common = ["--keystore", str(path), "--ledger", service.url]
    assert runner.invoke(app, ["register", *common]).exit_code == 0
    cid = str(CID.from_block(identity.address.encode()))
    first = runner.invoke(app, ["advertise", cid, *common])
    assert first.exit_code == 0, first.output
    assert "first      yes" in first.output
    assert f"first by   {identity.address}" in first.output

    second = runner.invoke(app, ["advertise", cid, "--json", *common])
    assert second.exit_code == 0, second.output
    answer = json.loads(second.stdout)
    assert (answer["cid"], answer["first"], answer["count"]) == (cid, False, 2)
    assert answer["first_advertiser"] == identity.address
    listed = httpx.get(f"{service.url}/v1/advertisements", params={"cid": cid}).json()
    first_time = datetime.fromtimestamp(listed["advertisements"][0]["timestamp"], UTC)
    assert answer["first_time"] == first_time.isoformat().replace("+00:00", "Z")

    listed = httpx.get(f"{service.url}/v1/advertisements", params={"cid": cid}).json()
    assert [row["first"] for row in listed["advertisements"]] == [True, False]
    assert {row["advertiser"] for row in listed["advertisements"]} == {identity.address}


def test_an_unregistered_robot_cannot_advertise(
    service: Service, keystore: Path, identity: Identity
) -> None:
    path = keystore
    common = ["--keystore", str(path), "--ledger", service.url]
    refused = runner.invoke(app, ["advertise", DATA_CID, *common])
    assert refused.exit_code == 4
    assert refused.stderr == (
        "error: reverted: Registry: advertiser is not an active robot "
        "(hint: run `robocloud register` first)\n"
    )
    listed = httpx.get(f"{service.url}/v1/advertisements", params={"cid": DATA_CID}).json()
    assert listed == {"advertisements": []}
    gone = httpx.get(f"{service.url}/v1/robots/{identity.address}")
    assert gone.status_code == 404
    assert gone.json()["error"]["code"] == "robot_not_found"


def test_a_bad_cid_is_refused_before_anything_is_sent(
    service: Service, keystore: Path, identity: Identity
) -> None:
    path = keystore
    refused = runner.invoke(
        app, ["advertise", "not-a-cid", "--keystore", str(path), "--ledger", service.url]
    )
    assert refused.exit_code == 2
    assert "is not a CID" in refused.output


def test_an_unregistered_robot_is_told_to_register_by_a_registered_only_cas(
    service: Service,
    keystore: Path,
    identity: Identity,
    service_factory: ServiceFactory,
    tmp_path: Path,
) -> None:
    """A cas that accepts only registered robots: refused with the hint, then accepted."""
    path = keystore
    cas = service_factory(
        "cas", {"ROBOCLOUD_AUTH": "registered", "ROBOCLOUD_LEDGER_URL": service.url}
    )
    source = tmp_path / "notes.txt"
    source.write_bytes(b"Hello world")
    put = ["put", str(source), "--keystore", str(path), "--cas", cas.url]
    refused = runner.invoke(app, put)
    assert refused.exit_code == 4
    assert refused.stderr.startswith(f"error: 403 address_not_allowed: address {identity.address}")
    assert refused.stderr.endswith(
        "(hint: run `robocloud register` to register this robot on the ledger)\n"
    )
    assert refused.stdout == ""
    assert httpx.post(f"{cas.url}/api/v0/pin/ls").json() == {"Keys": {}}

    registered = runner.invoke(app, ["register", "--keystore", str(path), "--ledger", service.url])
    assert registered.exit_code == 0, registered.output
    accepted = until_accepted(put)
    assert accepted.exit_code == 0, accepted.output
    assert accepted.stdout == f"{DATA_CID}\n"


def until_accepted(args: list[str], timeout_s: float = 30.0) -> Result:
    """Run a command until it succeeds: the cas remembers an unregistered signer briefly."""
    deadline = time.monotonic() + timeout_s
    while True:
        result = runner.invoke(app, args)
        if result.exit_code == 0 or time.monotonic() > deadline:
            return result
        time.sleep(0.2)


def test_a_ledger_answering_deeply_nested_json_is_refused_in_one_line() -> None:
    """What segfaulted ``robocloud robot``: 100,000 nested brackets from a hostile service."""
    with scripted_server(lambda _: json_reply(nested_json(100_000))) as hostile:
        done = subprocess.run(
            [str(Path(sys.executable).with_name("robocloud")), "robot", ADDRESS],
            capture_output=True,
            text=True,
            env={**os.environ, "ROBOCLOUD_LEDGER_URL": hostile.url},
            timeout=120,
        )
    assert done.returncode == 6, done.stderr
    assert done.stdout == ""
    assert done.stderr.startswith(f"error: the ledger service at {hostile.url} sent an answer")
    assert "nested deeper than 64 levels" in done.stderr
    assert done.stderr.count("\n") == 1
