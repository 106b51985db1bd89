"""The ledger commands refuse bad input before touching the key or the network."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from robocloud.cli import app
from robocloud.identity import Identity
from tests.procs import free_port

runner = CliRunner()


@pytest.mark.parametrize(
    "args",
    [
        ["advertise", "not-a-cid"],
        [
            "advertise",
            "bafkreid33n22tcydu7pk2egzkyq4phh5mjwhyf6son6zggnlnlyi3257um",
            "--description",
            "x",
        ],
        ["register", "--metadata", "0x02"],
    ],
)
def test_bad_cids_exit_2_without_asking_for_the_key(args: list[str], tmp_path: Path) -> None:
    missing = tmp_path / "no-keystore.json"
    result = runner.invoke(app, [*args, "--keystore", str(missing)])
    assert result.exit_code == 2
    assert "is not a CID" in result.output
    assert not missing.exists()


def test_unreachable_ledger_is_a_clear_error(tmp_path: Path) -> None:
    keystore = tmp_path / "key.json"
    Identity.generate().save(keystore, "pw", scrypt_n=2**4)
    url = f"http://127.0.0.1:{free_port()}"
    result = runner.invoke(app, ["robot", "--keystore", str(keystore), "--ledger", url])
    assert result.exit_code == 3
    assert result.stderr.startswith(f"error: cannot connect to the ledger service at {url}")
    assert "ROBOCLOUD_LEDGER_URL or --ledger" in result.stderr
    assert result.stdout == ""


def test_robot_without_keystore_or_address_names_the_missing_file(tmp_path: Path) -> None:
    missing = tmp_path / "none.json"
    result = runner.invoke(app, ["robot", "--keystore", str(missing)])
    assert result.exit_code == 1
    assert str(missing) in result.output.replace("\n", "")
