"""UnixFS directories against kubo's fixtures and js-ipfs-unixfs's importer on the same trees."""

from __future__ import annotations

from pathlib import Path

import pytest

from robocloud.car import CarReader
from robocloud.cid import CID, DAG_PB
from robocloud.dagpb import Link, PBNode
from robocloud.directory import (
    DirectoryBuilder,
    NotADirectory,
    PathNotFound,
    directory_node,
    list_entries,
    resolve,
    sharded_directory,
)
from robocloud.unixfs import (
    HAMT_SHARD,
    MURMUR3_X64_64,
    ImportParams,
    UnixfsData,
    UnixfsError,
    file_range_blocks,
    import_bytes,
    walk_dag,
)
from tests.procs import SHARED_DATA
from tests.reference import reference_cid, write_tree

FIXTURES = SHARED_DATA / "ipfs" / "car" / "gateway-conformance"
V1 = ImportParams.from_options(cid_version=1)
V0 = ImportParams.from_options()


def build_tree(root: Path, params: ImportParams) -> tuple[dict[str, CID], dict[CID, bytes]]:
    """Import every file under ``root`` and build its directories; CIDs by path, and blocks."""
    builder = DirectoryBuilder(params.cid_version, block_sized_shards=params.block_sized_shards)
    store: dict[CID, bytes] = {}
    for path in sorted(root.rglob("*")):
        relative = path.relative_to(root).as_posix()
        if path.is_dir():
            builder.add_directory(relative)
            continue
        blocks, cid = import_bytes(path.read_bytes(), params)
        store.update((block.cid, block.data) for block in blocks)
        builder.add_file(relative, cid, sum(len(block.data) for block in blocks))
    built = builder.finish()
    for directory in built.values():
        store.update((block.cid, block.data) for block in directory.blocks)
    return {path: directory.link.cid for path, directory in built.items()}, store


def car_blocks(name: str) -> tuple[CID, dict[CID, bytes]]:
    with (FIXTURES / name).open("rb") as stream:
        reader = CarReader(stream)
        blocks = {block.cid: block.data for block in reader}
    return reader.roots[0], blocks


def test_empty_directories_have_kubos_cids() -> None:
    assert str(directory_node([], 1)[1].cid) == (
        "bafybeiczsscdsbs7ffqz55asqdf3smv6klcw3gofszvwlyarci47bgf354"
    )
    assert str(directory_node([], 0)[1].cid) == "QmUNLLsPACCz1vLxQVkXqqLX5R1X345qqfHbsf67hvA3Nn"


def test_the_gateway_conformance_directory_imports_to_its_cids() -> None:
    v1, _ = build_tree(FIXTURES / "dag_car_input" / "dir", V1)
    assert str(v1[""]) == "bafybeidlbwbu73tbjr3atntjz4lq5ego5w2uyof35vvwcnheaftzi3rndu"
    assert str(v1["subdir"]) == "bafybeiaq6e55xratife7s5cmzjcmwy4adzzlk74sbdpfcq72gus6cweeeq"
    v0, _ = build_tree(FIXTURES / "dag_car_input" / "dir", V0)
    assert str(v0[""]) == "QmQaY7A59b66t6HfRW5smaffKwmNxtDxmWr7QB78R2Bxbs"


def test_kubo_add_rw_wraps_a_directory_as_the_fixture_was_made() -> None:
    """gateway-raw-block.car: ``ipfs add -Qrw --cid-version 1 dir`` of dir/ascii.txt."""
    blocks, cid = import_bytes(b"hello application/vnd.ipld.raw\n", V1)
    builder = DirectoryBuilder(1)
    builder.add_file("dir/ascii.txt", cid, sum(len(block.data) for block in blocks))
    assert builder.finish()[""].link.cid == car_blocks("gateway-raw-block.car")[0]


def test_kubo_add_r_with_a_tiny_chunker_as_the_fixture_was_made() -> None:
    """tooling-car-issue-54.car: ``ipfs add -Qr --chunker=size-5 dir-54`` (CIDv0)."""
    params = ImportParams.from_options(chunker="size-5")
    builder = DirectoryBuilder(0)
    for path, text in (("sub1/hello.txt", b"abc123\n"), ("sub2/hello.txt", b"xyz456\n")):
        blocks, cid = import_bytes(text, params)
        builder.add_file(path, cid, sum(len(block.data) for block in blocks))
    assert builder.finish()[""].link.cid == car_blocks("tooling-car-issue-54.car")[0]


def test_the_hamt_fixture_rebuilds_byte_for_byte_and_resolves_every_name() -> None:
    root, blocks = car_blocks("single-layer-hamt-with-multi-block-files.car")
    entries = list(list_entries(root, blocks.__getitem__))
    assert len(entries) == 1000
    rebuilt, link = sharded_directory(entries, 1)  # the fixture was sharded below the threshold
    assert link.cid == root
    assert {block.cid for block in rebuilt} <= set(blocks)
    for entry in entries[::37]:
        found = resolve(root, [entry.name], blocks.__getitem__)
        assert found.cid == entry.cid
        assert found.path_blocks[0] == root
    with pytest.raises(PathNotFound) as missing:
        resolve(root, ["no-such-file.txt"], blocks.__getitem__)
    assert (missing.value.segment, missing.value.at) == ("no-such-file.txt", root)


def test_paths_resolve_through_directories_and_stop_at_files() -> None:
    cids, store = build_tree(FIXTURES / "dag_car_input" / "dir", V1)
    found = resolve(cids[""], ["subdir", "leaf.txt"], store.__getitem__)
    assert str(found.cid) == "bafkreihdhgb5vyuqu7jssreyo3h567obewtqq37fi5hr2w4um5icacry7m"
    assert found.path_blocks == [cids[""], cids["subdir"]]
    with pytest.raises(NotADirectory) as through_file:
        resolve(cids[""], ["a-file.txt", "x"], store.__getitem__)
    assert through_file.value.segment == "x"
    names = sorted(entry.name for entry in list_entries(cids[""], store.__getitem__))
    assert names == ["a-file.txt", "b-file.txt", "subdir"]


@pytest.mark.parametrize(
    "path", ["..", "a/../b", "a//b", "/abs", "./x/.", "a/\x00", "n" * 256], ids=repr
)
def test_paths_that_escape_or_are_malformed_are_refused(path: str) -> None:
    with pytest.raises(UnixfsError):
        DirectoryBuilder().add_file(path, CID.from_block(b"x"), 1)


def test_a_name_both_file_and_directory_is_refused() -> None:
    builder = DirectoryBuilder()
    builder.add_file("a", CID.from_block(b"x"), 1)
    builder.add_file("a/b", CID.from_block(b"y"), 1)
    with pytest.raises(UnixfsError, match="both a file and a directory"):
        builder.finish()


# ---- against js-ipfs-unixfs (tests/reference), same trees, same options ----


@pytest.fixture(scope="module")
def ten_thousand(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("hamt") / "dir"
    return write_tree(root, {f"file-{i:05d}.txt": f"file {i}\n".encode() for i in range(10_000)})


@pytest.mark.parametrize(
    ("params", "args"), [(V1, ("1", "true")), (V0, ("0", "false"))], ids=["v1", "v0"]
)
def test_ten_thousand_entries_shard_as_the_reference_does(
    ten_thousand: Path, params: ImportParams, args: tuple[str, str]
) -> None:
    ours, store = build_tree(ten_thousand, params)
    assert str(ours[""]) == reference_cid(ten_thousand, *args)
    listed = list(list_entries(ours[""], store.__getitem__))
    assert len(listed) == 10_000
    assert resolve(ours[""], ["file-04242.txt"], store.__getitem__).cid == next(
        entry.cid for entry in listed if entry.name == "file-04242.txt"
    )


def test_odd_names_and_deep_nesting_match_the_reference(tmp_path: Path) -> None:
    files = {
        "with space.txt": b"a",
        "ünïcödé/日本語.txt": b"b",
        "percent%41%.bin": b"c",
        "a/b/c/d/e/deep.txt": b"d",
        "empty.bin": b"",
    }
    root = write_tree(tmp_path / "odd", files)
    (root / "empty-dir").mkdir()
    ours, _ = build_tree(root, V1)
    assert str(ours[""]) == reference_cid(root)


def test_the_v1_2025_profile_shards_by_block_size_as_the_reference_does(tmp_path: Path) -> None:
    """Just past the threshold by exact block size, still under it by name-plus-CID size."""
    root = write_tree(tmp_path / "near", {f"{i:04d}-{'x' * 60}": b"" for i in range(2_500)})
    profile = ImportParams.from_options(profile="unixfs-v1-2025")
    ours, store = build_tree(root, profile)
    assert str(ours[""]) == reference_cid(root, "1", "true", "unixfs-v1-2025")
    legacy, _ = build_tree(root, V1)
    assert legacy[""] != ours[""]
    assert ours[""] in store


def test_an_entity_walk_of_a_hamt_takes_every_shard_level_and_no_entry() -> None:
    """237 of the fixture's 243 blocks: every shard (two levels), none of the 6 file blocks."""
    root, blocks = car_blocks("single-layer-hamt-with-multi-block-files.car")
    entity = list(walk_dag(root, blocks.__getitem__, "entity"))
    assert len(entity) == 237
    assert entity[0].cid == root
    assert len(list(walk_dag(root, blocks.__getitem__, "all"))) == len(blocks)


def test_a_byte_range_of_a_file_needs_only_the_blocks_that_cover_it() -> None:
    data = bytes(range(256)) * 4096  # four 256 KiB leaves under one root
    blocks, root = import_bytes(data, V1)
    store = {block.cid: block.data for block in blocks}
    leaves = [block.cid for block in blocks if block.cid != root]
    chunk = 262_144
    covering = list(file_range_blocks(root, store.__getitem__, chunk + 10, 2 * chunk + 1))
    assert [block.cid for block in covering] == [root, leaves[1], leaves[2]]
    assert [block.cid for block in file_range_blocks(root, store.__getitem__, 0, 0)] == [root]


def repeating_hamt(levels: int) -> tuple[CID, dict[CID, bytes]]:
    """HAMT shards that link one sub-shard under all 256 buckets, ``levels`` deep: 256 **
    levels entries from ``levels + 1`` blocks (a 37 KB CAR for three levels)."""
    leaf = CID.from_block(b"x")
    blocks = {leaf: b"x"}
    links = [Link(leaf, f"{i:02X}file{i}", 1) for i in range(256)]
    for _ in range(levels):
        shard = UnixfsData(HAMT_SHARD, hash_type=MURMUR3_X64_64, fanout=256)
        encoded = PBNode(links, shard.encode()).encode()
        cid = CID.from_block(encoded, DAG_PB)
        blocks[cid] = encoded
        links = [Link(cid, f"{i:02X}", 0) for i in range(256)]
    return cid, blocks


def test_a_hamt_linking_one_shard_twice_is_refused_before_its_entries_multiply() -> None:
    root, blocks = repeating_hamt(3)
    listed = list_entries(root, blocks.__getitem__)
    assert sum(1 for _ in zip(range(256), listed, strict=False)) == 256
    with pytest.raises(UnixfsError, match=f"links the shard {list(blocks)[1]} twice"):
        list(listed)


def test_a_hamt_shard_with_more_links_than_its_fanout_is_refused() -> None:
    leaf = CID.from_block(b"x")
    shard = UnixfsData(HAMT_SHARD, hash_type=MURMUR3_X64_64, fanout=16)
    links = [Link(leaf, f"{i % 16:X}name{i}", 1) for i in range(17)]
    encoded = PBNode(links, shard.encode()).encode()
    root = CID.from_block(encoded, DAG_PB)
    with pytest.raises(UnixfsError, match="has 17 links, more than its fanout 16"):
        list(list_entries(root, {root: encoded, leaf: b"x"}.__getitem__))
