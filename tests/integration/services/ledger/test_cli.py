"""``robocloud register``, ``advertise`` and ``robot`` against a real ledger service."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest
from typer.testing import CliRunner

from robocloud.cid import CID
from robocloud.cli import app
from robocloud.identity import Identity
from tests.integration.services.ledger.conftest import Service

runner = CliRunner()
DATA_CID = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"


@pytest.fixture
def keystore(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, Identity]:
    identity = Identity.generate()
    path = tmp_path / "key.json"
    identity.save(path, "pw", scrypt_n=2**4)
    monkeypatch.setenv("ROBOCLOUD_PASSPHRASE", "pw")
    return path, identity


def test_register_funds_registers_and_is_idempotent(
    service: Service, keystore: tuple[Path, Identity]
) -> None:
    path, identity = keystore
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
    assert "state      active" in shown.output


def test_advertise_records_the_first_advertiser(
    service: Service, keystore: tuple[Path, Identity]
) -> None:
    path, identity = keystore
    common = ["--keystore", str(path), "--ledger", service.url]
    assert runner.invoke(app, ["register", *common]).exit_code == 0
    cid = str(CID.from_block(identity.address.encode()))
    first = runner.invoke(app, ["advertise", cid, *common])
    assert first.exit_code == 0, first.output
    assert "first      yes" in first.output
    assert f"first by   {identity.address}" in first.output

    second = runner.invoke(app, ["advertise", cid, *common])
    assert second.exit_code == 0, second.output
    assert "first      no" in second.output
    assert "count      2" in second.output

    listed = httpx.get(f"{service.url}/v1/advertisements", params={"cid": cid}).json()
    assert [row["first"] for row in listed["advertisements"]] == [True, False]
    assert {row["advertiser"] for row in listed["advertisements"]} == {identity.address}


def test_an_unregistered_robot_cannot_advertise(
    service: Service, keystore: tuple[Path, Identity]
) -> None:
    path, identity = keystore
    common = ["--keystore", str(path), "--ledger", service.url]
    refused = runner.invoke(app, ["advertise", DATA_CID, *common])
    assert refused.exit_code == 1
    assert "reverted: Registry: advertiser is not an active robot" in refused.output
    listed = httpx.get(f"{service.url}/v1/advertisements", params={"cid": DATA_CID}).json()
    assert listed == {"advertisements": []}
    gone = httpx.get(f"{service.url}/v1/robots/{identity.address}")
    assert gone.status_code == 404
    assert gone.json()["error"]["code"] == "robot_not_found"


def test_a_bad_cid_is_refused_before_anything_is_sent(
    service: Service, keystore: tuple[Path, Identity]
) -> None:
    path, _ = keystore
    refused = runner.invoke(
        app, ["advertise", "not-a-cid", "--keystore", str(path), "--ledger", service.url]
    )
    assert refused.exit_code == 2
    assert "is not a CID" in refused.output
