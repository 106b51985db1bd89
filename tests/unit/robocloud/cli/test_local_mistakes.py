"""Mistakes made on the robot's own machine are its own: a usage error (2) or a local problem
(1) in one line, never exit 6 ("the service is broken"), never a traceback. Each of these
happens before any service is asked, so the URLs below point at nothing."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from robocloud.cli import app
from robocloud.identity import Identity
from tests.procs import free_port

runner = CliRunner()
NOWHERE = f"http://127.0.0.1:{free_port()}"


@pytest.mark.parametrize("command", ["show", "submit"])
def test_a_bad_template_id_is_a_usage_error(command: str) -> None:
    result = runner.invoke(app, ["templates", command, "bad id", "--storage", NOWHERE])
    assert result.exit_code == 2, result.output
    assert "'bad id' is not a template id (name@version)" in result.stderr


def test_a_template_file_that_is_not_a_template_document_is_a_usage_error(
    tmp_path: Path, keystore: Path
) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    result = runner.invoke(
        app, ["templates", "create", str(bad), "--storage", NOWHERE, "-k", str(keystore)]
    )
    assert result.exit_code == 2, result.output
    assert result.stderr.startswith(f"error: {bad}: ")
    assert "the service is broken" not in result.stderr


@pytest.mark.parametrize("source", ["file", "stdin"])
def test_a_sparql_query_that_is_not_utf8_is_a_usage_error(tmp_path: Path, source: str) -> None:
    query = tmp_path / "q.rq"
    query.write_bytes(b"SELECT * WHERE { ?s ?p \xff }")
    argument = f"@{query}" if source == "file" else "-"
    result = runner.invoke(
        app, ["sparql", argument, "--storage", NOWHERE], input=query.read_bytes()
    )
    assert result.exit_code == 2, result.output
    assert "is not UTF-8 text" in re.sub(r"[\s│]+", " ", result.stderr)


def test_no_passphrase_and_no_terminal_says_which_setting_gives_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """click's own "Aborted!" (exit 1) said neither what was missing nor how to give it."""
    monkeypatch.delenv("ROBOCLOUD_PASSPHRASE", raising=False)
    path = tmp_path / "key.json"
    Identity.generate().save(path, "pw", scrypt_n=2**4)
    result = runner.invoke(app, ["templates", "submit", "imu@1", "-k", str(path)], input="")
    assert result.exit_code == 1, result.output
    assert "no passphrase given" in result.stderr
    assert "ROBOCLOUD_PASSPHRASE" in result.stderr


def test_keys_show_of_a_keystore_with_a_malformed_address_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "key.json"
    path.write_text(json.dumps({"address": "zz"}))
    result = runner.invoke(app, ["keys", "show", "-k", str(path)])
    assert result.exit_code == 1, result.output
    assert result.stderr.startswith(f"error: {path} has a malformed address: 'zz'")
