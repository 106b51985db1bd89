"""The Approved registration mode end to end: a ledger, a cas that admits registered robots only,
and the CLI as robots and the admin use it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import pytest
from typer.testing import CliRunner, Result

from robocloud.cas import Cas
from robocloud.cid import CID
from robocloud.cli import app
from robocloud.errors import PermissionDeniedError
from robocloud.identity import Identity
from tests.conftest import ServiceFactory
from tests.integration.services.ledger.conftest import PASSPHRASE, start_ledger
from tests.procs import ServiceProcess

runner = CliRunner()


@pytest.fixture(scope="module")
def ledger(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    process = start_ledger(
        tmp_path_factory.mktemp("approved") / "data",
        {"ROBOCLOUD_LEDGER_REGISTRATION_MODE": "approved"},
    )
    try:
        yield process
    finally:
        process.stop()


@pytest.fixture
def cas(ledger: ServiceProcess, service_factory: ServiceFactory) -> ServiceProcess:
    return service_factory(
        "cas",
        {
            "ROBOCLOUD_AUTH": "registered",
            "ROBOCLOUD_LEDGER_URL": ledger.url,
            "ROBOCLOUD_CAS_GC_INTERVAL_S": "0",
        },
    )


Cli = Callable[..., Result]


@pytest.fixture
def cli(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, ledger: ServiceProcess) -> Cli:
    """Run ``robocloud`` as the holder of ``key``: a robot's keystore, or the admin's."""
    monkeypatch.setenv("ROBOCLOUD_LEDGER_URL", ledger.url)

    def invoke(*args: str, key: Path | None = None, passphrase: str = "pw") -> Result:
        monkeypatch.setenv("ROBOCLOUD_PASSPHRASE", passphrase)
        keystore = ["--keystore", str(key)] if key is not None else []
        result = runner.invoke(app, [*args, *keystore])
        assert result.exit_code == 0, result.output
        return result

    return invoke


def new_robot(tmp_path: Path, name: str) -> tuple[Identity, Path]:
    identity = Identity.generate()
    path = tmp_path / f"{name}.json"
    identity.save(path, "pw", scrypt_n=2**4)
    return identity, path


def admin_key(ledger: ServiceProcess) -> Path:
    return ledger.data_dir / "keys" / "admin.json"


def write(cas: ServiceProcess, robot: Identity, data: bytes) -> str:
    with Cas(cas.url, robot, retries=0) as client:
        return str(client.add_bytes(data))


def refused_write(cas: ServiceProcess, robot: Identity) -> PermissionDeniedError:
    """The cas's refusal of ``robot``'s write; it stored nothing."""
    data = b"refused " + robot.address.encode()
    with pytest.raises(PermissionDeniedError) as denied:
        write(cas, robot, data)
    assert httpx.get(f"{cas.url}/ipfs/{CID.from_block(data)}").status_code == 404
    return denied.value


def refused(cas: ServiceProcess, robot: Identity) -> str:
    return refused_write(cas, robot).code


def eventually_writes(cas: ServiceProcess, robot: Identity, data: bytes) -> str:
    """The cas caches a "not registered" answer for 2 s: poll until the approval shows."""
    deadline = time.monotonic() + 30
    while True:
        try:
            return write(cas, robot, data)
        except PermissionDeniedError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def test_a_registration_waits_for_the_admin_then_the_robot_writes(
    ledger: ServiceProcess, cas: ServiceProcess, cli: Cli, tmp_path: Path
) -> None:
    robot, key = new_robot(tmp_path, "robot")
    asked = cli("register", key=key)
    assert "awaits approval by the admin or a registrar" in asked.stdout
    record = httpx.get(f"{ledger.url}/v1/robots/{robot.address}").json()
    assert (record["status"], record["active"], record["roles"]) == ("pending", False, [])
    pending = refused_write(cas, robot)
    assert (pending.code, pending.details) == ("registration_pending", {"address": robot.address})
    assert "awaits approval by the ledger's admin or a registrar" in pending.message
    waiting = json.loads(cli("admin", "pending", "--json").stdout)
    assert waiting[-1]["address"] == robot.address, "oldest first: the newest request is last"
    shown = cli("robot", robot.address)
    assert "pending approval" in shown.stdout

    approved = cli("admin", "approve", robot.address, key=admin_key(ledger), passphrase=PASSPHRASE)
    assert f"{robot.address} approved" in approved.stdout
    assert eventually_writes(cas, robot, b"admitted") == str(CID.from_block(b"admitted"))
    assert httpx.get(f"{cas.url}/ipfs/{CID.from_block(b'admitted')}").content == b"admitted"
    record = httpx.get(f"{ledger.url}/v1/robots/{robot.address}").json()
    assert (record["status"], record["active"]) == ("registered", True)
    waiting = json.loads(cli("admin", "pending", "--json").stdout)
    assert robot.address not in [entry["address"] for entry in waiting]


def test_a_rejected_robot_stays_out_and_may_ask_again(
    ledger: ServiceProcess, cas: ServiceProcess, cli: Cli, tmp_path: Path
) -> None:
    robot, key = new_robot(tmp_path, "robot")
    cli("register", key=key)
    cli("admin", "reject", robot.address, key=admin_key(ledger), passphrase=PASSPHRASE)
    assert httpx.get(f"{ledger.url}/v1/robots/{robot.address}").status_code == 404
    assert refused(cas, robot) == "address_not_allowed"
    again = cli("register", "--json", key=key)
    assert json.loads(again.stdout)["pending"] is True


def test_a_registrar_approves_without_the_admin_key(
    ledger: ServiceProcess, cas: ServiceProcess, cli: Cli, tmp_path: Path
) -> None:
    registrar, registrar_key = new_robot(tmp_path, "registrar")
    cli("register", key=registrar_key)
    cli("admin", "approve", registrar.address, key=admin_key(ledger), passphrase=PASSPHRASE)
    cli(
        "admin",
        "grant",
        registrar.address,
        "registrar",
        key=admin_key(ledger),
        passphrase=PASSPHRASE,
    )
    robot, key = new_robot(tmp_path, "robot")
    cli("register", key=key)
    cli("admin", "approve", robot.address, key=registrar_key)
    assert eventually_writes(cas, robot, b"vouched for") == str(CID.from_block(b"vouched for"))
    stranger, stranger_key = new_robot(tmp_path, "stranger")
    cli("register", key=stranger_key)
    not_a_registrar = runner.invoke(
        app, ["admin", "approve", stranger.address, "--keystore", str(key)]
    )
    assert not_a_registrar.exit_code != 0
    assert "caller is not a registrar" in not_a_registrar.output


def failed(*args: str, key: Path, passphrase: str = "pw") -> Result:
    """Run ``robocloud`` expecting a failure: one line on stderr, no traceback."""
    result = runner.invoke(
        app, [*args, "--keystore", str(key)], env={"ROBOCLOUD_PASSPHRASE": passphrase}
    )
    assert result.exit_code != 0, result.output
    assert result.output.startswith("error: "), result.output
    assert "Traceback" not in result.output
    return result


def test_the_admin_suspends_revokes_and_reinstates(
    ledger: ServiceProcess, cas: ServiceProcess, cli: Cli, tmp_path: Path
) -> None:
    admin = {"key": admin_key(ledger), "passphrase": PASSPHRASE}
    registrar, registrar_key = new_robot(tmp_path, "registrar")
    cli("register", key=registrar_key)
    cli("admin", "approve", registrar.address, **admin)
    cli("admin", "grant", registrar.address, "registrar", **admin)
    suspended = json.loads(cli("admin", "suspend", registrar.address, "--json", **admin).stdout)
    assert (suspended["address"], suspended["action"]) == (registrar.address, "suspended")
    assert "state      suspended" in cli("robot", registrar.address).stdout
    with pytest.raises(PermissionDeniedError) as inactive:
        write(cas, registrar, b"suspended")
    assert inactive.value.code == "robot_inactive"

    robot, key = new_robot(tmp_path, "robot")
    cli("register", key=key)
    refused = failed("admin", "approve", robot.address, key=registrar_key)
    assert refused.exit_code == 4
    assert "caller is not a registrar" in refused.output
    assert "registrar role" in refused.output
    cli("admin", "reinstate", registrar.address, **admin)
    assert "state      active" in cli("robot", registrar.address).stdout
    cli("admin", "revoke", registrar.address, "registrar", **admin)
    record = httpx.get(f"{ledger.url}/v1/robots/{registrar.address}").json()
    assert (record["active"], record["roles"]) == (True, [])
    assert failed("admin", "approve", robot.address, key=registrar_key).exit_code == 4
    assert "pending approval" in cli("robot", robot.address).stdout


def test_refused_admin_commands_change_nothing(
    ledger: ServiceProcess, cli: Cli, tmp_path: Path
) -> None:
    robot, key = new_robot(tmp_path, "robot")
    cli("register", key=key)
    stranger, _ = new_robot(tmp_path, "stranger")
    not_pending = failed(
        "admin", "approve", stranger.address, key=admin_key(ledger), passphrase=PASSPHRASE
    )
    assert not_pending.exit_code == 4
    assert "no pending registration" in not_pending.output
    assert "robocloud admin pending" in not_pending.output
    wrong_passphrase = failed("admin", "approve", robot.address, key=admin_key(ledger))
    assert wrong_passphrase.exit_code == 1
    not_the_admin = failed("admin", "mode", "open", key=key)
    assert not_the_admin.exit_code == 4
    assert "caller is not the admin" in not_the_admin.output
    for args in (
        ["admin", "approve", "0x1234"],
        ["admin", "grant", robot.address, "overlord"],
        ["admin", "mode", "closed"],
    ):
        bad = runner.invoke(app, [*args, "--keystore", str(admin_key(ledger))])
        assert bad.exit_code == 2, bad.output
    record = httpx.get(f"{ledger.url}/v1/robots/{robot.address}").json()
    assert record["status"] == "pending"
    mode = json.loads(cli("admin", "mode", "--json").stdout)
    assert mode == {"mode": "approved"}
    listed = cli("admin", "pending").stdout
    assert robot.address in listed
    assert stranger.address not in listed


def test_restarting_in_open_mode_opens_registration(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    data = tmp_path / "ledger"
    approved = start_ledger(data, {"ROBOCLOUD_LEDGER_REGISTRATION_MODE": "approved"})
    try:
        mode = runner.invoke(app, ["admin", "mode", "--json", "--ledger", approved.url])
        assert json.loads(mode.stdout) == {"mode": "approved"}
    finally:
        approved.stop()
    opened = start_ledger(data, {"ROBOCLOUD_LEDGER_REGISTRATION_MODE": "open"})
    monkeypatch.setenv("ROBOCLOUD_PASSPHRASE", "pw")
    try:
        _, key = new_robot(tmp_path, "robot")
        answer = runner.invoke(
            app, ["register", "--json", "--keystore", str(key), "--ledger", opened.url]
        )
        assert answer.exit_code == 0, answer.output
        assert json.loads(answer.stdout)["registered"] is True
        mode = runner.invoke(app, ["admin", "mode", "--json", "--ledger", opened.url])
        assert json.loads(mode.stdout) == {"mode": "open"}
    finally:
        opened.stop()


@pytest.mark.parametrize(
    ("limit", "status", "code", "detail"),
    [
        ("0", 400, "invalid_limit", {"limit": 0}),
        ("-1", 400, "invalid_limit", {"limit": -1}),
        ("1001", 400, "invalid_limit", {"limit": 1001}),
        ("abc", 422, "validation_error", None),
        ("9" * 5000, 422, "validation_error", None),
    ],
    ids=["zero", "negative", "above-max", "text", "5000-digits"],
)
def test_the_pending_list_refuses_bad_limits_by_name(
    ledger: ServiceProcess, limit: str, status: int, code: str, detail: dict[str, int] | None
) -> None:
    answer = httpx.get(f"{ledger.url}/v1/registrations", params={"limit": limit})
    error = answer.json()["error"]
    assert (answer.status_code, error["code"]) == (status, code)
    if detail is not None:
        assert error["details"] == detail
    else:
        assert [field["field"] for field in error["details"]["errors"]] == ["query.limit"]
    assert httpx.get(f"{ledger.url}/readyz").status_code == 200


def test_the_pending_list_is_oldest_first_and_bounded(
    ledger: ServiceProcess, cli: Cli, tmp_path: Path
) -> None:
    for name in ("first", "second"):
        cli("register", key=new_robot(tmp_path, name)[1])
    everyone = httpx.get(f"{ledger.url}/v1/registrations").json()["pending"]
    blocks = [entry["registered_block"] for entry in everyone]
    assert len(everyone) >= 2
    assert blocks == sorted(blocks)
    assert all(entry["status"] == "pending" for entry in everyone)
    oldest = httpx.get(f"{ledger.url}/v1/registrations", params={"limit": 1}).json()["pending"]
    assert oldest == everyone[:1]
