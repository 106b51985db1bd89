"""``robocloud put DIR`` and ``Cas.add_directory``: the CID ``ipfs add -r`` gives the same tree."""

from __future__ import annotations

import io
import json
import os
from collections.abc import Callable
from pathlib import Path
from urllib.parse import quote

import httpx
import pytest
from typer.testing import CliRunner

from robocloud.car import CarReader, write_car
from robocloud.cas import (
    Cas,
    CasError,
    ContentTooLargeError,
    LocalContentError,
    NotAFileError,
    Tree,
)
from robocloud.cid import CID, Block, parse_cid
from robocloud.cli import app
from robocloud.client import ServiceClient
from robocloud.dagpb import Link, PBNode
from robocloud.directory import DirectoryBuilder
from robocloud.unixfs import DIRECTORY, UnixfsData, import_bytes, walk_dag
from tests.integration.services.cas.conftest import (
    multipart,
    pin_list,
    post_files,
    store_unchanged,
)
from tests.procs import SHARED_DATA, ServiceProcess
from tests.reference import reference_cid, write_tree
from tests.scripted_http import Exchange, scripted_server

runner = CliRunner()
CAR_FIXTURES = SHARED_DATA / "ipfs" / "car" / "gateway-conformance"
FIXTURE_DIR = CAR_FIXTURES / "dag_car_input" / "dir"
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


def tree_of(root: Path) -> dict[str, bytes | None]:
    """Every path under ``root``: a file's bytes, None for a directory."""
    return {
        str(path.relative_to(root)): None if path.is_dir() else path.read_bytes()
        for path in root.rglob("*")
    }


def test_get_writes_a_directory_back_as_it_was_put(
    cas: Cas, cas_service: ServiceProcess, tmp_path: Path
) -> None:
    """``robocloud put DIR`` took a folder as ``ipfs add -r`` does, and ``get`` refused its
    CID ("a directory, not a file"): a robot could share a folder and nobody could fetch it.
    It now writes the tree, five levels, odd names and an empty directory included."""
    root = write_tree(tmp_path / "tree", NESTED)
    (root / "empty").mkdir()
    directory = cas.add_directory(root)
    assert str(directory) == reference_cid(root)
    with pytest.raises(NotAFileError, match=f"{directory} is a directory, not a file"):
        cas.get_to_file(directory, tmp_path / "file")
    with pytest.raises(NotADirectoryError, match="is not a directory"):
        cas.get_tree(cas.add_bytes(b"a file"), tmp_path / "file")

    got = runner.invoke(
        app, ["get", str(directory), "-o", str(tmp_path / "out"), "--cas", cas_service.url]
    )

    assert got.exit_code == 0, got.output
    size = sum(len(data) for data in NESTED.values())
    assert got.stdout == f"{directory} -> {tmp_path / 'out'} (5 files, {size} bytes, verified)\n"
    assert tree_of(tmp_path / "out") == tree_of(root)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["out", "tree"]
    again = runner.invoke(
        app, ["get", str(directory), "-o", str(tmp_path / "out"), "--cas", cas_service.url]
    )
    assert again.exit_code == 1
    assert f"{tmp_path / 'out'} exists" in again.stderr
    assert tree_of(tmp_path / "out") == tree_of(root)


class CountingTransport(httpx.HTTPTransport):
    """Every request the SDK sends, as ``path?query``."""

    def __init__(self) -> None:
        super().__init__()
        self.sent: list[str] = []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        self.sent.append(f"{request.url.path}?{request.url.query.decode()}")
        return super().handle_request(request)


def test_get_fetches_a_whole_tree_in_one_request(
    cas: Cas, cas_service: ServiceProcess, tmp_path: Path
) -> None:
    """This tree came back in 58 requests (one a file, two for a file of several blocks: its
    root block, then its CAR; one a directory): 2.2 s for 1,000 small files on loopback, far
    longer from a distant gateway. One CAR of the whole tree now brings it. An entry the tree
    holds twice (a file, a directory, an empty one) is in that CAR once and is copied from
    the first; a block the CAR carried once and another file needs again (a chunk two files
    share) is fetched alone."""
    shared = bytes(range(256)) * 1024  # one chunk
    files = {f"a/file-{n:02d}.txt": f"file {n}\n".encode() * (n + 1) for n in range(40)}
    files |= {"b/same.bin": shared + b"b", "c/same.bin": shared + b"b", "d/other.bin": shared}
    root = write_tree(tmp_path / "tree", files)
    (root / "a" / "empty").mkdir()
    (root / "e").mkdir()
    directory = cas.add_directory(root)
    assert str(directory) == reference_cid(root)
    counting = CountingTransport()

    with Cas(cas_service.url, retries=0, transport=counting) as client:
        tree = client.get_tree(directory, tmp_path / "out")

    assert tree_of(tmp_path / "out") == tree_of(root)
    assert (tree.files, tree.directories) == (43, 7)
    assert tree.size == sum(len(data) for data in files.values())
    assert counting.sent == [
        f"/ipfs/{directory}?format=car&dag-scope=all",
        f"/ipfs/{CID.from_block(shared)}?format=raw",
    ]


def test_a_copied_entry_counts_against_the_bounds(cas: Cas, tmp_path: Path) -> None:
    """What a copy holds is counted as if it had been fetched: a directory held twice does
    not pass the entry bound or the size bound by being copied."""
    files = {"a/one.bin": b"1" * 1000, "a/two.bin": b"2" * 1000, "b/x.txt": b"x"}
    root = write_tree(
        tmp_path / "tree", files | {"c/one.bin": b"1" * 1000, "c/two.bin": b"2" * 1000}
    )
    directory = cas.add_directory(root)
    with pytest.raises(CasError, match="more than 8 entries"):
        cas.get_tree(directory, tmp_path / "out", max_entries=8)
    with pytest.raises(ContentTooLargeError, match=r"declares 2000 bytes, more than .* 1999 bytes"):
        cas.get_tree(directory, tmp_path / "out", max_size=4000)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["tree"]
    assert cas.get_tree(directory, tmp_path / "out", max_entries=9, max_size=4001) == Tree(
        5, 4, 4001
    )


LIED_TREE = {
    "x/big.bin": bytes(range(251)) * 3000,
    "x/small.txt": b"small\n",
    "y/copy.bin": bytes(range(251)) * 3000,
    "z.txt": b"z\n",
}


def local_tree(files: dict[str, bytes]) -> tuple[CID, list[Block]]:
    """The tree ``files`` as robocloud builds it, its blocks in the order of an honest CAR
    (depth first, each block once)."""
    store: dict[CID, bytes] = {}
    builder = DirectoryBuilder()
    for path, data in files.items():
        blocks, cid = import_bytes(data)
        store |= {block.cid: block.data for block in blocks}
        builder.add_file(path, cid, sum(len(block.data) for block in blocks))
    for built in builder.finish().values():
        store |= {block.cid: block.data for block in built.blocks}
    root = builder.finish()[""].link.cid
    return root, list(walk_dag(root, store.__getitem__))


def forged(blocks: list[Block]) -> list[Block]:
    """``blocks`` with the last one's bytes changed under its CID."""
    return [*blocks[:-1], Block(blocks[-1].cid, b"forged")]


@pytest.mark.parametrize(
    ("lie", "refusal"),
    [
        (lambda blocks: blocks[::-1], None),
        (lambda blocks: [block for block in blocks for _ in range(2)], None),
        (lambda blocks: blocks[:1], None),
        (forged, "does not match"),
    ],
    ids=["reordered", "repeated", "cut-short", "forged"],
)
def test_get_of_a_tree_takes_only_verified_blocks_from_a_lying_gateway(
    tmp_path: Path, lie: Callable[[list[Block]], list[Block]], refusal: str | None
) -> None:
    """The tree's CAR is the gateway's word: a block out of the order of the walk, repeated
    or missing is fetched alone, each verified against its CID, so the tree is written as
    it was put; a block whose bytes are not its CID's fails the download, leaving nothing."""
    root, blocks = local_tree(LIED_TREE)
    store = {block.cid: block.data for block in blocks}
    car = b"".join(write_car([root], lie(blocks)))

    def gateway(exchange: Exchange) -> tuple[int, dict[str, str], bytes]:
        cid = parse_cid(exchange.path.split("?")[0].removeprefix("/ipfs/"))
        if "format=raw" in exchange.path:
            return 200, {"Content-Type": "application/vnd.ipld.raw"}, store[cid]
        return 200, {"Content-Type": "application/vnd.ipld.car"}, car

    with scripted_server(gateway) as server, Cas(server.url, retries=0) as client:
        if refusal is None:
            tree = client.get_tree(root, tmp_path / "out")
        else:
            with pytest.raises(CasError, match=refusal):
                client.get_tree(root, tmp_path / "out")
    if refusal is None:
        assert tree_of(tmp_path / "out") == {"x": None, "y": None, **LIED_TREE}
        assert tree == Tree(4, 3, sum(len(data) for data in LIED_TREE.values()))
    else:
        assert list(tmp_path.iterdir()) == []


def imported_fixture(signed: ServiceClient, name: str) -> CID:
    """A gateway-conformance CAR imported into cas: its root."""
    data = (CAR_FIXTURES / name).read_bytes()
    answer = post_files(signed, "/api/v0/dag/import", (name, data))
    assert answer.status_code == 200, answer.text
    (root,) = CarReader(io.BytesIO(data)).roots
    return root


def test_get_writes_a_sharded_directory_of_multi_block_files(
    cas: Cas, cas_service: ServiceProcess, signed: ServiceClient, tmp_path: Path
) -> None:
    """gateway-conformance's HAMT-sharded directory: each file as the gateway serves it."""
    root = imported_fixture(signed, "single-layer-hamt-with-multi-block-files.car")
    tree = cas.get_tree(root, tmp_path / "out")
    names = sorted(path.name for path in (tmp_path / "out").iterdir())
    assert (tree.files, tree.directories, len(names)) == (len(names), 1, len(names))
    assert len(names) > 1
    with httpx.Client(base_url=cas_service.url) as gateway:  # 1,000 names: one connection
        for name in names:
            served = gateway.get(f"/ipfs/{root}/{quote(name)}")
            assert served.status_code == 200, served.text
            assert (tmp_path / "out" / name).read_bytes() == served.content
    assert tree.size == sum((tmp_path / "out" / name).stat().st_size for name in names)


def put_directory_node(signed: ServiceClient, links: list[Link]) -> CID:
    """A dag-pb directory over ``links`` exactly as given (any name), put as one block."""
    node = PBNode(links, UnixfsData(DIRECTORY).encode()).encode()
    body, content_type = multipart(("node", node))
    answer = signed.request(
        "POST",
        "/api/v0/block/put",
        params={"cid-codec": "dag-pb"},
        content=body,
        headers={"Content-Type": content_type},
    )
    return parse_cid(answer.json()["Key"])


@pytest.mark.parametrize("name", ["..", "a/b", "."])
def test_a_directory_naming_a_path_outside_is_refused_and_nothing_is_left(
    cas: Cas, signed: ServiceClient, tmp_path: Path, name: str
) -> None:
    """A directory is a stranger's: an entry named ``..`` or ``a/b`` would write beside or
    below the output. Refused naming the entry; the partial tree is removed."""
    leaf = cas.add_bytes(b"escaped\n")
    inner = put_directory_node(signed, [Link(leaf, "fine.txt", 8)])
    hostile = put_directory_node(signed, [Link(inner, "sub", 100), Link(leaf, name, 8)])
    target = tmp_path / "inside" / "out"
    target.parent.mkdir()
    with pytest.raises(CasError, match=f"{name!r} is not a valid directory entry name"):
        cas.get_tree(hostile, target)
    assert list(target.parent.iterdir()) == []
    assert sorted(path.name for path in tmp_path.iterdir()) == ["inside"]


def test_a_directory_past_its_bounds_is_refused_and_nothing_is_left(
    cas: Cas, tmp_path: Path
) -> None:
    """Sizes and counts are the DAG's word: the files' bytes in all, and the entries."""
    root = write_tree(tmp_path / "tree", NESTED)
    directory = cas.add_directory(root)
    biggest = max(len(data) for data in NESTED.values())
    with pytest.raises(ContentTooLargeError):
        cas.get_tree(directory, tmp_path / "out", max_size=biggest + 10)
    with pytest.raises(CasError, match="more than 6 entries"):
        cas.get_tree(directory, tmp_path / "out", max_entries=6)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["tree"]


def test_a_directory_holding_a_symbolic_link_is_refused(
    cas: Cas, cas_service: ServiceProcess, signed: ServiceClient, tmp_path: Path
) -> None:
    """robocloud writes no symbolic link (one could point anywhere): exit 2, nothing left."""
    root = imported_fixture(signed, "symlink.car")
    got = runner.invoke(
        app, ["get", str(root), "-o", str(tmp_path / "out"), "--cas", cas_service.url]
    )
    assert got.exit_code == 2, got.output
    assert "is a symbolic link, not a file" in got.stderr
    assert list(tmp_path.iterdir()) == []


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


def test_cat_and_get_take_a_path_inside_a_directory(
    cas: Cas, cas_service: ServiceProcess, tmp_path: Path
) -> None:
    """``CID/PATH`` as ``ipfs cat`` takes it, every directory block on the way verified: a
    file's bytes or range, and a subdirectory written whole. A path the directory does not
    hold is the asker's mistake (exit 2), named; so is one with ``..`` or an empty segment,
    refused before anything is asked."""
    root = write_tree(tmp_path / "tree", NESTED)
    directory = cas.add_directory(root)
    common = ["--cas", cas_service.url]

    whole = runner.invoke(app, ["cat", f"{directory}/a b/space name.txt", *common])
    assert (whole.exit_code, whole.stdout_bytes) == (0, NESTED["a b/space name.txt"])
    part = runner.invoke(
        app, ["cat", f"{directory}/top.txt", "--offset", "1", "--length", "2", *common]
    )
    assert part.stdout_bytes == b"op"
    got = runner.invoke(app, ["get", f"{directory}/a b/ä ö", "-o", str(tmp_path / "out"), *common])
    assert got.exit_code == 0, got.output
    assert tree_of(tmp_path / "out") == tree_of(root / "a b" / "ä ö")

    missing = runner.invoke(app, ["cat", f"{directory}/a b/nope.txt", *common])
    assert missing.exit_code == 2
    assert f"{directory}/a b/nope.txt: " in missing.stderr
    assert "has no entry 'nope.txt'" in missing.stderr
    through_a_file = runner.invoke(app, ["cat", f"{directory}/top.txt/x", *common])
    assert through_a_file.exit_code == 2
    assert "is not a directory" in through_a_file.stderr
    for bad, why in (
        ("../top.txt", "'..' is not a valid directory entry name"),
        ("/top.txt", "'/top.txt' is not a relative path"),
    ):
        refused = runner.invoke(app, ["cat", f"{directory}/{bad}", "--cas", "http://127.0.0.1:9"])
        assert refused.exit_code == 2, refused.output
        assert why in " ".join(refused.output.replace("│", " ").split())
    assert sorted(path.name for path in tmp_path.iterdir()) == ["out", "tree"]
