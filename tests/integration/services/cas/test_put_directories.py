"""``robocloud put DIR`` and ``Cas.add_directory``: the CID ``ipfs add -r`` gives the same tree."""

from __future__ import annotations

import json
import os
from pathlib import Path
from urllib.parse import quote

import httpx
import pytest
from typer.testing import CliRunner

from robocloud.cas import Cas, CasError
from robocloud.cli import app
from tests.integration.services.cas.conftest import pin_list, store_unchanged
from tests.procs import SHARED_DATA, ServiceProcess
from tests.reference import reference_cid, write_tree

runner = CliRunner()
FIXTURE_DIR = SHARED_DATA / "ipfs" / "car" / "gateway-conformance" / "dag_car_input" / "dir"
EMPTY_DIRECTORY = "bafybeiczsscdsbs7ffqz55asqdf3smv6klcw3gofszvwlyarci47bgf354"
NESTED = {
    "a b/ä ö/100%/d4/d5/deep.txt": b"five levels down\n",
    "a b/ä ö/100%/sibling.bin": bytes(range(256)) * 2000,
    "a b/space name.txt": b"spaces\n",
    "%41 not escaped.txt": b"percent\n",
    "top.txt": b"top\n",
}


@pytest.fixture(scope="module")
def cas_service(shared_cas_service: ServiceProcess) -> ServiceProcess:
    return shared_cas_service


def test_the_fixture_directory_adds_to_kubos_cid(cas: Cas) -> None:
    seen: list[int] = []
    cid = cas.add_directory(FIXTURE_DIR, progress=seen.append)
    assert str(cid) == "bafybeidlbwbu73tbjr3atntjz4lq5ego5w2uyof35vvwcnheaftzi3rndu"
    assert sum(seen) == sum(p.stat().st_size for p in FIXTURE_DIR.rglob("*") if p.is_file())


def test_a_tree_five_deep_with_odd_names_matches_the_reference_and_reads_back(
    cas: Cas, cas_service: ServiceProcess, tmp_path: Path
) -> None:
    root = write_tree(tmp_path / "tree", NESTED)
    (root / "empty").mkdir()
    cid = cas.add_directory(root)
    assert str(cid) == reference_cid(root)
    for path, data in NESTED.items():
        answer = httpx.get(f"{cas_service.url}/ipfs/{cid}/{quote(path)}")
        assert answer.status_code == 200, (path, answer.text)
        assert answer.content == data
    assert str(cid) in pin_list(cas_service.url)["Keys"]


def test_an_empty_directory_is_the_empty_unixfs_directory(cas: Cas, tmp_path: Path) -> None:
    (tmp_path / "nothing").mkdir()
    assert str(cas.add_directory(tmp_path / "nothing")) == EMPTY_DIRECTORY


def test_dotfiles_are_left_out_unless_asked_for(cas: Cas, tmp_path: Path) -> None:
    root = write_tree(tmp_path / "tree", {"seen.txt": b"a"})
    without = reference_cid(root)
    write_tree(root, {".hidden": b"b", ".git/config": b"c"})
    assert str(cas.add_directory(root)) == without
    assert str(cas.add_directory(root, hidden=True)) == reference_cid(root)


def test_a_symbolic_link_is_refused_before_anything_is_sent(
    cas: Cas, cas_service: ServiceProcess, tmp_path: Path
) -> None:
    root = write_tree(tmp_path / "tree", {"real.txt": b"real"})
    os.symlink(root / "real.txt", root / "link.txt")
    with store_unchanged(cas_service), pytest.raises(CasError, match="symbolic link"):
        cas.add_directory(root)


def test_cli_put_of_a_directory_prints_its_cid(
    cas_service: ServiceProcess, keystore: Path, tmp_path: Path
) -> None:
    root = write_tree(tmp_path / "tree", NESTED)
    common = ["--cas", cas_service.url, "--keystore", str(keystore)]
    put = runner.invoke(app, ["put", str(root), *common])
    assert put.exit_code == 0, put.output
    assert put.stdout.strip() == reference_cid(root)
    as_json = runner.invoke(app, ["put", str(root), "--no-pin", "--json", *common])
    assert json.loads(as_json.stdout) == {
        "cid": put.stdout.strip(),
        "size": sum(len(data) for data in NESTED.values()),
        "pinned": False,
    }


def test_cli_put_hidden_includes_dotfiles(
    cas_service: ServiceProcess, keystore: Path, tmp_path: Path
) -> None:
    root = write_tree(tmp_path / "tree", {"seen.txt": b"a", ".hidden": b"b"})
    common = ["--cas", cas_service.url, "--keystore", str(keystore)]
    put = runner.invoke(app, ["put", str(root), "--hidden", *common])
    assert put.exit_code == 0, put.output
    assert put.stdout.strip() == reference_cid(root)
