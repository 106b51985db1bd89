"""``robocloud put DIR`` and ``Cas.add_directory``: the CID ``ipfs add -r`` gives the same tree."""

from __future__ import annotations

import json
import os
from pathlib import Path
from urllib.parse import quote

import httpx
import pytest
from typer.testing import CliRunner

from robocloud.cas import Cas, LocalContentError, NotAFileError
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
    cas: Cas, cas_service: ServiceProcess, keystore: Path, tmp_path: Path
) -> None:
    """A local problem, exit 1: it was a CasError, which says the gateway cannot be
    trusted (exit 6, "the service is broken")."""
    root = write_tree(tmp_path / "tree", {"real.txt": b"real"})
    os.symlink(root / "real.txt", root / "link.txt")
    with store_unchanged(cas_service), pytest.raises(LocalContentError, match="symbolic link"):
        cas.add_directory(root)
    with store_unchanged(cas_service):
        put = runner.invoke(app, ["put", str(root), "--cas", cas_service.url, "-k", str(keystore)])
    assert put.exit_code == 1
    assert "link.txt' is a symbolic link" in put.stderr


def test_a_name_that_is_not_utf8_is_refused_naming_the_file(
    cas: Cas, cas_service: ServiceProcess, keystore: Path, tmp_path: Path
) -> None:
    """A Latin-1 name (from a FAT USB stick) raised UnicodeEncodeError, a traceback."""
    root = write_tree(tmp_path / "tree", {"fine.txt": b"fine"})
    latin = root / os.fsdecode(b"caf\xe9.txt")
    latin.write_bytes(b"latin-1 name")
    with store_unchanged(cas_service):
        for add in (lambda: cas.add_directory(root), lambda: cas.add_file(latin)):
            with pytest.raises(LocalContentError, match=r"caf\\xe9.txt' has a name that is not"):
                add()
        put = runner.invoke(app, ["put", str(root), "--cas", cas_service.url, "-k", str(keystore)])
    assert put.exit_code == 1, put.output
    assert "not UTF-8" in put.stderr


@pytest.mark.parametrize("given", [".", "./", "sub/.."])
def test_put_of_the_current_directory_stores_it_under_its_name(
    cas_service: ServiceProcess,
    keystore: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    given: str,
) -> None:
    """``Path(".").name`` is empty, so every part went as ``/a.txt`` and was refused (400
    invalid_path); ``ipfs add -r .`` names the directory as the shell's working one."""
    root = write_tree(tmp_path / "here", {"a.txt": b"a", "sub/b.txt": b"b"})
    monkeypatch.chdir(root)
    put = runner.invoke(app, ["put", given, "--cas", cas_service.url, "-k", str(keystore)])
    assert put.exit_code == 0, put.output
    assert put.stdout.strip() == reference_cid(root)


def test_get_of_a_directory_is_a_usage_error_and_writes_nothing(
    cas: Cas, cas_service: ServiceProcess, tmp_path: Path
) -> None:
    """The root is verified against its CID, so its type is a fact about what was asked
    for: exit 2, not exit 6 blaming the service."""
    directory = cas.add_directory(write_tree(tmp_path / "tree", {"a.txt": b"a"}))
    target = tmp_path / "out"
    with pytest.raises(NotAFileError, match=f"{directory} is a directory, not a file"):
        cas.get_to_file(directory, target)
    got = runner.invoke(app, ["get", str(directory), "-o", str(target), "--cas", cas_service.url])
    assert got.exit_code == 2, got.output
    assert "is a directory, not a file" in got.stderr
    assert sorted(path.name for path in tmp_path.iterdir()) == ["tree"]


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
