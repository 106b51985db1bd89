"""``Cas.get_to_file`` and ``robocloud get`` beside files they did not create.

A download goes to a partial file beside its target first. In a shared directory another
user can plant a file or a symbolic link under any name there, so the partial file must be
a new one: the planted link's target is never written, truncated or removed, whether the
download succeeds or is refused.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from robocloud.car import write_car
from robocloud.cas import Cas, CasError
from robocloud.cid import CID
from robocloud.cli import app
from tests.scripted_http import scripted_server

CONTENT = b"attacker-chosen content\n"
ROOT = CID.from_block(CONTENT)
CAR = b"".join(write_car([ROOT], [(ROOT, CONTENT)]))
runner = CliRunner()


@pytest.fixture
def planted(tmp_path: Path) -> Iterator[Path]:
    """A victim file, and symbolic links to it under every partial name the old code used."""
    victim = tmp_path / "victim_config.txt"
    victim.write_text("precious settings\n")
    (tmp_path / ".out.partial").symlink_to(victim)
    yield victim
    assert victim.read_text() == "precious settings\n"
    assert (tmp_path / ".out.partial").readlink() == victim


def gateway(car: bytes) -> Iterator[str]:
    with scripted_server(lambda _: (200, {"Content-Type": "application/vnd.ipld.car"}, car)) as s:
        yield s.url


def test_a_verified_download_never_writes_through_a_planted_link(
    tmp_path: Path, planted: Path
) -> None:
    previous = os.umask(0o022)
    try:
        for url in gateway(CAR):
            with Cas(url, retries=0) as cas:
                assert cas.get_to_file(ROOT, tmp_path / "out", overwrite=False) == len(CONTENT)
    finally:
        os.umask(previous)
    out = tmp_path / "out"
    assert not out.is_symlink()
    assert out.read_bytes() == CONTENT
    assert stat.S_IMODE(out.stat().st_mode) == 0o644
    assert sorted(p.name for p in tmp_path.iterdir()) == [".out.partial", "out", planted.name]


def test_a_refused_download_leaves_the_planted_links_target_whole(
    tmp_path: Path, planted: Path
) -> None:
    for url in gateway(CAR[:-5]):
        with Cas(url, retries=0) as cas, pytest.raises(CasError, match="truncated"):
            cas.get_to_file(ROOT, tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == [".out.partial", planted.name]


def test_the_cli_refuses_a_lying_gateway_without_touching_the_planted_links_target(
    tmp_path: Path, planted: Path
) -> None:
    for url in gateway(CAR[:-5]):
        result = runner.invoke(app, ["get", str(ROOT), "-o", str(tmp_path / "out"), "--cas", url])
    assert result.exit_code == 6, result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == [".out.partial", planted.name]
