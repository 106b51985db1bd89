"""``robocloud ingest --drafts DIR`` against a scripted storage node: each draft appears whole
under the name the node chose, and a file that exists (an operator's edited draft) is kept
unless ``--overwrite``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

import robocloud as robocloud_package
from robocloud.cli import app
from tests.scripted_http import Script, json_reply, scripted_server

runner = CliRunner()


def draft(name: str) -> dict[str, Any]:
    return {"name": name, "version": 1, "fields": {"x": "float"}, "description": f"{name} draft"}


def storage_node(
    drafted: tuple[str, ...] = ("imu", "gps"), fits: list[str] | None = None, **fields: Any
) -> Script:
    """A node whose ingest job succeeded, proposing a draft (with ``fields``) for each unbound
    topic, of ``drafted`` names: topics of one type share theirs. The first one's draft has
    the fields of the approved templates ``fits``."""
    topics = [
        {"topic": f"/{name}_{index}", "msgtype": "m", "template": None, "skipped": "unbound"}
        | {"draft": draft(name) | fields, "fits": (fits or []) if index == 0 else []}
        for index, name in enumerate(drafted)
    ]
    job = {
        "id": "j1",
        "status": "succeeded",
        "messages": {"done": 1, "total": 1},
        "records": {"staged": 0, "committed": 0},
        "topics": topics,
        "error": None,
        "updated_ns": 1,
    }
    return lambda _: json_reply(json.dumps(job))


def ingest(
    keystore: Path,
    tmp_path: Path,
    *options: str,
    drafted: tuple[str, ...] = ("imu", "gps"),
    fits: list[str] | None = None,
) -> Any:
    bag = tmp_path / "x.mcap"
    bag.write_bytes(b"\x89MCAP0\r\n" + bytes(64))
    with scripted_server(storage_node(drafted, fits)) as node:
        return runner.invoke(
            app,
            ["ingest", str(bag), "--storage", node.url, "--keystore", str(keystore), *options],
        )


@pytest.mark.parametrize(
    ("drafted", "files"),
    [(("imu", "gps"), ["gps.json", "imu.json"]), (("tf", "tf", "gps"), ["gps.json", "tf.json"])],
)
def test_drafts_are_written_whole_under_their_names_once_each(
    keystore: Path, tmp_path: Path, drafted: tuple[str, ...], files: list[str]
) -> None:
    """``/tf`` and ``/tf_static`` share their type's draft: the second write found the first's
    file and the ingest failed, "these files exist and were kept", in a new directory."""
    drafts = tmp_path / "drafts"
    result = ingest(keystore, tmp_path, "--drafts", str(drafts), drafted=drafted)
    assert result.exit_code == 0, result.output
    assert sorted(path.name for path in drafts.iterdir()) == files
    assert json.loads((drafts / files[1]).read_text()) == draft(drafted[0])


def test_an_unbound_topic_names_the_approved_template_it_fits(
    keystore: Path, tmp_path: Path
) -> None:
    result = ingest(keystore, tmp_path, fits=["imu@1", "imu@3"])
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    assert lines[1] == "  /imu_0 (m): unbound; imu@3 fits it: robocloud bind imu@3 --topic /imu_0"
    assert lines[2] == "  /gps_1 (m): unbound"


def test_a_draft_file_holding_the_draft_already_is_no_edit_kept(
    keystore: Path, tmp_path: Path
) -> None:
    """The same bag ingested twice, or two bags of one type, into one --drafts directory:
    the second run exited 1, "these files exist and were kept", for files it wrote itself."""
    drafts = tmp_path / "drafts"
    assert ingest(keystore, tmp_path, "--drafts", str(drafts)).exit_code == 0
    again = ingest(keystore, tmp_path, "--drafts", str(drafts))
    assert again.exit_code == 0, again.output
    assert json.loads((drafts / "imu.json").read_text()) == draft("imu")


def test_a_fifo_under_a_drafts_name_is_kept_and_never_waited_on(
    keystore: Path, tmp_path: Path
) -> None:
    drafts = tmp_path / "drafts"
    drafts.mkdir()
    os.mkfifo(drafts / "imu.json")
    result = ingest(keystore, tmp_path, "--drafts", str(drafts))
    assert result.exit_code == 1, result.output
    assert str(drafts / "imu.json") in result.stderr
    assert (drafts / "imu.json").is_fifo()


def test_a_draft_file_that_exists_is_kept_and_named(keystore: Path, tmp_path: Path) -> None:
    """It was replaced, an operator's edit of an earlier draft lost to the next ingest."""
    drafts = tmp_path / "drafts"
    drafts.mkdir()
    (drafts / "imu.json").write_text("my edit\n")
    result = ingest(keystore, tmp_path, "--drafts", str(drafts))
    assert result.exit_code == 1, result.output
    assert "the ingest succeeded" in result.stderr
    assert str(drafts / "imu.json") in result.stderr
    assert "--overwrite" in result.stderr
    assert (drafts / "imu.json").read_text() == "my edit\n"
    assert json.loads((drafts / "gps.json").read_text()) == draft("gps")
    assert sorted(path.name for path in drafts.iterdir()) == ["gps.json", "imu.json"]


def test_a_link_planted_under_a_drafts_name_is_never_followed(
    keystore: Path, tmp_path: Path
) -> None:
    drafts = tmp_path / "drafts"
    drafts.mkdir()
    elsewhere = tmp_path / "elsewhere"
    (drafts / "imu.json").symlink_to(elsewhere)
    result = ingest(keystore, tmp_path, "--drafts", str(drafts))
    assert result.exit_code == 1, result.output
    assert not elsewhere.exists()


def test_overwrite_replaces_a_draft_file_that_exists(keystore: Path, tmp_path: Path) -> None:
    drafts = tmp_path / "drafts"
    drafts.mkdir()
    (drafts / "imu.json").write_text("my edit\n")
    result = ingest(keystore, tmp_path, "--drafts", str(drafts), "--overwrite")
    assert result.exit_code == 0, result.output
    assert json.loads((drafts / "imu.json").read_text()) == draft("imu")
    assert sorted(path.name for path in drafts.iterdir()) == ["gps.json", "imu.json"]


FILE_SIZE_LIMIT = 64 * 1024
CUT_SHORT = f"""
import os, resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, ({FILE_SIZE_LIMIT}, {FILE_SIZE_LIMIT}))
os.execv(sys.argv[1], sys.argv[1:])
"""
"""Runs a command whose writes past ``FILE_SIZE_LIMIT`` fail (EFBIG), as on a full disk."""


@pytest.mark.parametrize(
    ("existing", "options"), [({}, []), ({"imu.json": "my edit\n"}, ["--overwrite"])]
)
def test_a_write_cut_short_leaves_no_half_draft(
    keystore: Path, tmp_path: Path, existing: dict[str, str], options: list[str]
) -> None:
    """Each draft was written straight under its name: a write cut short (a full disk, an
    interrupt) left half a draft there, for ``templates create`` to read next, and with
    ``--overwrite`` the file it replaced already gone."""
    drafts = tmp_path / "drafts"
    drafts.mkdir()
    for name, text in existing.items():
        (drafts / name).write_text(text)
    bag = tmp_path / "x.mcap"
    bag.write_bytes(b"\x89MCAP0\r\n" + bytes(64))
    robocloud = Path(sys.executable).with_name("robocloud")
    with scripted_server(storage_node(description="d" * 2 * FILE_SIZE_LIMIT)) as node:
        command = [str(robocloud), "ingest", str(bag), "--storage", node.url]
        signed = ["--keystore", str(keystore), "--drafts", str(drafts), *options]
        done = subprocess.run(
            [sys.executable, "-c", CUT_SHORT, *command, *signed],
            capture_output=True,
            text=True,
            timeout=60,
            env={**os.environ, "PYTHONPATH": str(Path(robocloud_package.__file__).parents[1])},
        )
    assert done.returncode == 1, done.stderr
    assert "File too large" in done.stderr
    assert {path.name: path.read_text() for path in drafts.iterdir()} == existing
