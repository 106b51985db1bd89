"""The importer against IPFS's own vectors, the one reader (random access and the CAR-order
stream), ranges, the DAG walk; and DAGs built to hurt them: deeper than any importer makes,
lying about their sizes, wider than a node may be."""

from __future__ import annotations

import io
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from robocloud.car import CarReader, write_car
from robocloud.cid import CID, DAG_PB, RAW, Block
from robocloud.dagpb import MAX_LINKS, Link, PBNode, len_field
from robocloud.unixfs import (
    DIRECTORY,
    FILE,
    HAMT_SHARD,
    MAX_DAG_DEPTH,
    MURMUR3_X64_64,
    READ_ALLOWANCE,
    READ_FACTOR,
    Importer,
    ImportParams,
    UnixfsData,
    UnixfsError,
    assemble_file,
    file_range_blocks,
    file_size,
    import_bytes,
    list_directory,
    parse_chunker,
    read_budget,
    read_file,
    visit_budget,
    walk_dag,
)
from tests.unit.robocloud.ipfs_vectors import PROFILES, car_path, file_cases, input_named, vectors


@pytest.mark.parametrize(("name", "profile", "expected"), file_cases())
def test_import_gives_the_cid_of_ipfs_add(name: str, profile: str, expected: str) -> None:
    """Each vector of shared/data/ipfs/vectors.json (kubo test/cli and sharness, js-unixfs)."""
    _, root = import_bytes(input_named(name), PROFILES[profile])
    assert str(root) == expected


@pytest.mark.parametrize(
    ("size", "blocks", "codec"),
    [(0, 1, RAW), (11, 1, RAW), (262_143, 1, RAW), (262_144, 1, RAW), (262_145, 3, DAG_PB)],
)
def test_chunk_boundaries(size: int, blocks: int, codec: int) -> None:
    imported, root = import_bytes(b"x" * size)
    assert len(imported) == blocks
    assert root.codec == codec
    assert imported[-1].cid == root


def test_more_than_174_chunks_makes_a_two_level_tree() -> None:
    data = input_named("chacha20:v0-seed:45613057")
    blocks, root = import_bytes(data)
    store = dict(blocks)
    top = list_links(root, store)
    assert len(top) == 2
    assert len(list_links(top[0], store)) == 174
    assert len(list_links(top[1], store)) == 1
    assert len(blocks) == 175 + 3


def list_links(cid: CID, store: dict[CID, bytes]) -> list[CID]:
    return [link.cid for link in PBNode.decode(store[cid]).links]


def test_feeding_in_odd_pieces_gives_the_same_blocks() -> None:
    data = bytes(range(256)) * 4000
    whole, root = import_bytes(data, ImportParams(chunk_size=1000, max_links=3))
    importer = Importer(ImportParams(chunk_size=1000, max_links=3))
    pieces: list[Block] = []
    for start in range(0, len(data), 777):
        pieces += importer.feed(data[start : start + 777])
    tail, streamed_root, size = importer.finish()
    assert (pieces + tail, streamed_root, size) == (whole, root, len(data))


@pytest.mark.parametrize(
    ("offset", "length"),
    [(0, None), (0, 1), (999, 2), (1000, 1000), (5, 12_345), (255_999, None), (256_000, 10)],
)
def test_reader_returns_exact_ranges(offset: int, length: int | None) -> None:
    data = bytes(range(256)) * 1000
    blocks, root = import_bytes(data, ImportParams(chunk_size=1000, max_links=4))
    store = dict(blocks)
    fetched: list[CID] = []

    def get_block(cid: CID) -> bytes:
        fetched.append(cid)
        return store[cid]

    end = None if length is None else offset + length
    assert b"".join(read_file(root, get_block, offset, length)) == data[offset:end]
    assert file_size(root, store.__getitem__) == len(data)
    if length == 1:
        assert len(fetched) <= 5  # root, two inner levels, one leaf: not the whole file


def test_reader_reads_legacy_leaves_with_inline_data() -> None:
    data = b"legacy " * 100_000
    blocks, root = import_bytes(data, PROFILES["v0"])
    assert b"".join(read_file(root, dict(blocks).__getitem__, 3, 70_000)) == data[3:70_003]


def test_walk_scopes_follow_the_trustless_gateway() -> None:
    with car_path("car/gateway-conformance/subdir-with-mixed-block-files.car").open("rb") as car:
        reader = CarReader(car)
        store = {block.cid: block.data for block in reader}
    root = reader.roots[0]
    everything = [block.cid for block in walk_dag(root, store.__getitem__, "all")]
    assert sorted(map(str, everything)) == sorted(map(str, store))
    assert [block.cid for block in walk_dag(root, store.__getitem__, "block")] == [root]
    assert [block.cid for block in walk_dag(root, store.__getitem__, "entity")] == [root]
    data = (bytes(range(256)) * 12)[:3000]
    blocks, file_root = import_bytes(data, ImportParams(chunk_size=1000))
    walked = list(walk_dag(file_root, dict(blocks).__getitem__, "entity"))
    assert walked[0].cid == file_root
    assert sorted(b.cid.binary for b in walked) == sorted(b.cid.binary for b in blocks)


def test_directory_listing_matches_the_fixture() -> None:
    directory = vectors()["directories"][0]
    with car_path(directory["car"]).open("rb") as car:
        reader = CarReader(car)
        store = {block.cid: block.data for block in reader}
    entries = {
        link.name: str(link.cid) for link in list_directory(reader.roots[0], store.__getitem__)
    }
    expected = {k: v for k, v in directory["entries"].items() if "/" not in k}
    assert entries == expected
    assert str(reader.roots[0]) == directory["expected"][0]["cid"]


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"chunker": "rabin-1-2-3"}, "unsupported chunker"),
        ({"chunker": "size-0"}, "between 1 and"),
        ({"chunker": "size-99999999"}, "between 1 and"),
        ({"profile": "unixfs-v9"}, "unknown profile"),
        ({"cid_version": 2}, "cid-version"),
    ],
)
def test_bad_import_options_are_named(options: dict[str, object], message: str) -> None:
    with pytest.raises(UnixfsError, match=message):
        ImportParams.from_options(**options)  # type: ignore[arg-type]


def test_kubo_option_semantics() -> None:
    assert ImportParams.from_options(cid_version=1) == ImportParams()
    assert ImportParams.from_options(cid_version=1, raw_leaves=False).raw_leaves is False
    assert ImportParams.from_options().cid_version == 0
    assert parse_chunker("size-1048576") == 1_048_576


def test_reading_a_directory_as_a_file_is_an_error() -> None:
    with car_path("car/gateway-conformance/tooling-car-dag.car").open("rb") as car:
        reader = CarReader(car)
        store = {block.cid: block.data for block in reader}
    with pytest.raises(UnixfsError, match="not a file"):
        list(read_file(reader.roots[0], store.__getitem__))


def test_car_of_an_import_reads_back() -> None:
    blocks, root = import_bytes(b"z" * 600_000)
    car = b"".join(write_car([root], walk_dag(root, dict(blocks).__getitem__)))
    reader = CarReader(io.BytesIO(car))
    store = {block.cid: block.data for block in reader}
    assert reader.roots == [root]
    assert b"".join(read_file(root, store.__getitem__)) == b"z" * 600_000


# ---- the streamed reader: read_nodes over a CAR's blocks ----


def car_blocks(root: CID, store: dict[CID, bytes]) -> list[Block]:
    """The blocks of a file as a gateway's CAR carries them: depth first, each once."""
    car = b"".join(write_car([root], walk_dag(root, store.__getitem__, "entity")))
    return list(CarReader(io.BytesIO(car)))


def assembled(root: CID, blocks: list[Block], out_path: Path) -> bytes:
    progress: list[int] = []
    with out_path.open("w+b") as out:
        written = assemble_file(root, iter(blocks), out, progress.append)
    content = out_path.read_bytes()
    assert written == sum(progress) == len(content)
    return content


@pytest.mark.parametrize(
    ("name", "profile"),
    [
        ("chacha20:v0-seed:45613057", "v0"),
        ("chacha20:v0-seed:45613057", "v1-raw-256k"),
        ("chacha20_chunk-v1-seed_1048577.bin", "v1-2025"),
        ("empty.bin", "v0"),
    ],
)
def test_both_sources_read_the_vectors_back(name: str, profile: str, tmp_path: Path) -> None:
    data = input_named(name)
    blocks, root = import_bytes(data, PROFILES[profile])
    store = dict(blocks)
    assert b"".join(read_file(root, store.__getitem__)) == data
    assert assembled(root, car_blocks(root, store), tmp_path / "out") == data


@pytest.mark.parametrize("params", [ImportParams(), ImportParams(0, False)], ids=["raw", "pb"])
def test_repeated_blocks_sent_once_are_replayed_from_the_output(
    params: ImportParams, tmp_path: Path
) -> None:
    """Zeros make one leaf repeated 400 times and one inner node repeated twice."""
    data = b"\0" * (400 * 1024) + b"tail"
    blocks, root = import_bytes(data, ImportParams(params.cid_version, params.raw_leaves, 1024, 4))
    carried = car_blocks(root, dict(blocks))
    assert len(carried) < len(set(blocks)) + 1 < 400
    assert assembled(root, carried, tmp_path / "out") == data


def test_a_file_of_more_distinct_blocks_than_a_download_tracks_is_refused(
    tmp_path: Path,
) -> None:
    """Every distinct block is remembered for a repeat: 16-byte chunks of a 6 MB file made a
    robot hold 138 MiB; the bound stops such a file, a repeated block counts once."""
    data = b"".join(n.to_bytes(16, "big") for n in range(300))
    blocks, root = import_bytes(data, ImportParams(1, True, 16, 174))
    carried = car_blocks(root, dict(blocks))
    with (tmp_path / "out").open("w+b") as out:
        assert assemble_file(
            root, iter(carried), out, lambda _: None, max_nodes=len(carried)
        ) == len(data)
    with (tmp_path / "out2").open("w+b") as out, pytest.raises(UnixfsError) as refused:
        assemble_file(root, iter(carried), out, lambda _: None, max_nodes=len(carried) - 1)
    assert f"more than {len(carried) - 1} distinct blocks" in str(refused.value)


def zero_size_child_file() -> tuple[CID, dict[CID, bytes], bytes]:
    """A root with an empty raw leaf between two others, as some importers write."""
    leaves = [b"abc", b"", b"defg"]
    cids = [CID.from_block(leaf) for leaf in leaves]
    sizes = [len(leaf) for leaf in leaves]
    unixfs = UnixfsData(FILE, b"", sum(sizes), sizes)
    encoded = PBNode([Link(c, "", s) for c, s in zip(cids, sizes, strict=True)], unixfs.encode())
    root = CID.from_block(encoded.encode(), DAG_PB)
    return root, {root: encoded.encode(), **dict(zip(cids, leaves, strict=True))}, b"abcdefg"


def test_an_empty_child_is_read_by_both_sources(tmp_path: Path) -> None:
    root, store, data = zero_size_child_file()
    fetched: list[CID] = []

    def get_block(cid: CID) -> bytes:
        fetched.append(cid)
        return store[cid]

    assert b"".join(read_file(root, get_block)) == data
    assert len(fetched) == 4
    assert assembled(root, car_blocks(root, store), tmp_path / "out") == data
    assert b"".join(read_file(root, store.__getitem__, 2, 3)) == b"cde"


def test_the_stream_must_follow_the_dag(tmp_path: Path) -> None:
    blocks, root = import_bytes(bytes(range(256)) * 40, ImportParams(chunk_size=1000))
    carried = car_blocks(root, dict(blocks))
    stray = Block(CID.from_block(b"x"), b"x")
    for sent, message in (
        (carried[:-1], f"the blocks end before block {carried[-1].cid} of {root}"),
        ([carried[0], carried[2], carried[1], *carried[3:]], f"{carried[1].cid} of {root} is due"),
        ([*carried, stray], f"there are blocks beyond the file {root}"),
    ):
        with (tmp_path / "out").open("w+b") as out, pytest.raises(UnixfsError) as raised:
            assemble_file(root, iter(sent), out, lambda _: None)
        assert message in str(raised.value)


# ---- hostile DAGs ----

LEAF = b"x" * 10


def chain(depth: int, leaf: bytes = LEAF) -> tuple[CID, dict[CID, bytes]]:
    """A file whose one leaf hangs ``depth`` single-link nodes below its root."""
    leaf_cid = CID.from_block(leaf, RAW, 1)
    blocks = {leaf_cid: leaf}
    child, size = leaf_cid, len(leaf)
    for _ in range(depth):
        node = PBNode([Link(child, "", size)], UnixfsData(FILE, b"", size, [size]).encode())
        encoded = node.encode()
        child = CID.from_block(encoded, DAG_PB, 1)
        blocks[child] = encoded
    return child, blocks


def lying_root(declared: int, leaf: bytes = LEAF) -> tuple[CID, dict[CID, bytes]]:
    leaf_cid = CID.from_block(leaf, RAW, 1)
    unixfs = UnixfsData(FILE, b"", declared, [declared])
    encoded = PBNode([Link(leaf_cid, "", len(leaf))], unixfs.encode()).encode()
    root = CID.from_block(encoded, DAG_PB, 1)
    return root, {leaf_cid: leaf, root: encoded}


def dfs_blocks(root: CID, blocks: dict[CID, bytes]) -> list[Block]:
    """Every block in DFS order, as a CAR of a DAG that does not parse as a file would be."""
    order: list[Block] = []
    stack = [root]
    while stack:
        cid = stack.pop()
        order.append(Block(cid, blocks[cid]))
        if cid.codec == DAG_PB:
            stack.extend(reversed([link.cid for link in PBNode.decode(blocks[cid]).links]))
    return order


def stream_read(root: CID, blocks: dict[CID, bytes]) -> Callable[[], object]:
    def read() -> object:
        with io.BytesIO() as out:
            return assemble_file(root, iter(dfs_blocks(root, blocks)), out, lambda _: None)

    return read


def test_a_chain_at_the_limit_is_read_by_both_sources() -> None:
    root, blocks = chain(MAX_DAG_DEPTH)
    assert b"".join(read_file(root, blocks.__getitem__)) == LEAF
    assert stream_read(root, blocks)() == len(LEAF)
    assert len(list(walk_dag(root, blocks.__getitem__))) == MAX_DAG_DEPTH + 1


def test_a_chain_one_deeper_is_refused_naming_the_limit() -> None:
    root, blocks = chain(MAX_DAG_DEPTH + 1)
    message = f"deeper than {MAX_DAG_DEPTH} levels"
    for read in (
        lambda: b"".join(read_file(root, blocks.__getitem__)),
        stream_read(root, blocks),
        lambda: list(walk_dag(root, blocks.__getitem__)),
    ):
        with pytest.raises(UnixfsError, match=message):
            read()


HOSTILE_CHAIN_SCRIPT = """
import io, sys
sys.setrecursionlimit(100_000)
from robocloud.car import CarReader, write_car
from robocloud.unixfs import MAX_DAG_DEPTH, UnixfsError, assemble_file, file_size, read_file
from robocloud.unixfs import walk_dag
from tests.unit.robocloud.test_unixfs import chain, dfs_blocks

root, blocks = chain(30_000)
car = b"".join(write_car([root], dfs_blocks(root, blocks)))
print(len(car))
reader = CarReader(io.BytesIO(car))
store = {block.cid: block.data for block in reader}
print(file_size(root, store.__getitem__))
attempts = {
    "read": lambda: b"".join(read_file(root, store.__getitem__)),
    "stream": lambda: assemble_file(root, iter(dfs_blocks(root, store)), io.BytesIO(), print),
    "walk": lambda: list(walk_dag(root, store.__getitem__)),
}
for name, attempt in attempts.items():
    try:
        attempt()
    except UnixfsError as exc:
        assert f"deeper than {MAX_DAG_DEPTH} levels" in str(exc), exc
        print(name, "refused")
"""


def test_a_30000_deep_chain_is_refused_even_with_py_ecc_recursion_limit() -> None:
    """py_ecc sets the recursion limit to 100,000 at import: then the C stack is the limit,
    and recursion would crash the process instead of raising. The chain is a 2.6 MB CAR."""
    result = subprocess.run(
        [sys.executable, "-c", HOSTILE_CHAIN_SCRIPT],
        capture_output=True,
        timeout=300,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    size, declared, *refused = result.stdout.decode().splitlines()
    assert 2_500_000 < int(size) < 2_800_000
    assert int(declared) == len(LEAF)
    assert refused == ["read refused", "stream refused", "walk refused"]


@pytest.mark.parametrize("declared", [len(LEAF) + 1, 10**12, len(LEAF) - 1])
def test_a_root_declaring_another_size_than_its_leaves_hold_fails_reading(declared: int) -> None:
    root, blocks = lying_root(declared)
    assert file_size(root, blocks.__getitem__) == declared
    leaf = CID.from_block(LEAF)
    message = f"{leaf} holds {len(LEAF)} bytes but its parent in {root} declares {declared}"
    for read in (lambda: b"".join(read_file(root, blocks.__getitem__)), stream_read(root, blocks)):
        with pytest.raises(UnixfsError) as raised:
            read()
        assert message in str(raised.value)


def test_an_inner_node_that_lies_is_named_with_its_place_in_the_file() -> None:
    """The second of two subtrees declares 10 bytes where its leaf holds 9."""
    honest, store = chain(1)
    short = CID.from_block(b"y" * 9)
    liar = PBNode([Link(short, "", 9)], UnixfsData(FILE, b"", 10, [10]).encode()).encode()
    liar_cid = CID.from_block(liar, DAG_PB)
    root_node = PBNode(
        [Link(honest, "", 0), Link(liar_cid, "", 0)], UnixfsData(FILE, b"", 20, [10, 10]).encode()
    )
    root = CID.from_block(root_node.encode(), DAG_PB)
    store |= {short: b"y" * 9, liar_cid: liar, root: root_node.encode()}
    with pytest.raises(UnixfsError, match=f"{short} holds 9 bytes .* at byte 10 of the file"):
        b"".join(read_file(root, store.__getitem__))
    assert b"".join(read_file(root, store.__getitem__, 0, 10)) == LEAF


def test_filesize_disagreeing_with_the_blocksizes_is_refused_from_the_root() -> None:
    leaf_cid = CID.from_block(LEAF, RAW, 1)
    unixfs = UnixfsData(FILE, b"", 999, [len(LEAF)])
    encoded = PBNode([Link(leaf_cid, "", len(LEAF))], unixfs.encode()).encode()
    root = CID.from_block(encoded, DAG_PB, 1)
    with pytest.raises(UnixfsError, match=f"{root} declares a file of 999 bytes"):
        file_size(root, {root: encoded}.__getitem__)


def test_ranges_of_an_honest_chain_are_unaffected() -> None:
    root, blocks = chain(3)
    assert b"".join(read_file(root, blocks.__getitem__, 2, 5)) == LEAF[2:7]


def test_a_node_with_100000_links_is_refused_without_reading_a_child() -> None:
    leaf = CID.from_block(LEAF)
    count = 100_000
    one_link = PBNode([Link(leaf, "", len(LEAF))], None).encode()
    unixfs = UnixfsData(FILE, b"", count * len(LEAF), [len(LEAF)] * count)
    encoded = one_link * count + PBNode([], unixfs.encode()).encode()
    root = CID.from_block(encoded, DAG_PB)
    fetched: list[CID] = []

    def get_block(cid: CID) -> bytes:
        fetched.append(cid)
        return {root: encoded, leaf: LEAF}[cid]

    for read in (
        lambda: file_size(root, get_block),
        lambda: b"".join(read_file(root, get_block)),
        lambda: list(walk_dag(root, get_block)),
    ):
        with pytest.raises(
            UnixfsError, match=f"{root} is not a dag-pb node: more than {MAX_LINKS}"
        ):
            read()
    assert set(fetched) == {root}


@pytest.mark.parametrize(
    ("unixfs", "message"),
    [
        (b"", "UnixFS data without a type"),
        (b"\x08\x09", "unknown type 9"),
        (b"\x0a\x01\x02", "Type must be a varint"),
        (b"\x08\x02\x10\x05", "Data must be bytes"),
        (b"\x08\x02\x22\x05\x01", "field 4 at byte 2 declares 5 bytes but only 1 are left"),
    ],
)
def test_bad_unixfs_data_is_named_with_the_block(unixfs: bytes, message: str) -> None:
    encoded = PBNode([], unixfs).encode()
    cid = CID.from_block(encoded, DAG_PB)
    with pytest.raises(UnixfsError) as raised:
        file_size(cid, {cid: encoded}.__getitem__)
    assert str(cid) in str(raised.value)
    assert message in str(raised.value)


def test_entity_walks_follow_every_level_of_a_hamt_and_no_entry() -> None:
    """A 2-level HAMT (fanout 16: one hex digit per bucket) whose entries are not walked."""
    entry = CID.from_block(b"entry content")
    file_entry = PBNode([], UnixfsData(FILE, b"x", 1).encode()).encode()
    file_cid = CID.from_block(file_entry, DAG_PB)

    def shard(links: list[Link]) -> tuple[CID, bytes]:
        unixfs = UnixfsData(HAMT_SHARD, hash_type=MURMUR3_X64_64, fanout=16)
        encoded = PBNode(links, unixfs.encode()).encode()
        return CID.from_block(encoded, DAG_PB), encoded

    inner, inner_block = shard([Link(entry, "3name", 13)])
    middle, middle_block = shard([Link(inner, "A", 0), Link(file_cid, "7file", 1)])
    root, root_block = shard([Link(middle, "0", 0)])
    store = {root: root_block, middle: middle_block, inner: inner_block, file_cid: file_entry}
    walked = [block.cid for block in walk_dag(root, store.__getitem__, "entity")]
    assert walked == [root, middle, inner]
    directory = PBNode([Link(root, "sharded", 0)], UnixfsData(DIRECTORY).encode()).encode()
    top = CID.from_block(directory, DAG_PB)
    assert [b.cid for b in walk_dag(top, {top: directory}.__getitem__, "entity")] == [top]


def fan(child: CID, child_size: int, count: int) -> tuple[CID, bytes]:
    """A file node linking ``count`` times to the same child."""
    unixfs = UnixfsData(FILE, b"", count * child_size, [child_size] * count)
    encoded = PBNode([Link(child, "", child_size)] * count, unixfs.encode()).encode()
    return CID.from_block(encoded, DAG_PB), encoded


def test_a_dag_of_nothing_repeated_is_refused_after_its_visit_budget() -> None:
    """Seven blocks, each linking 174 times to the next: 174^6 visits for an empty file."""
    child = CID.from_block(b"")
    blocks = {child: b""}
    for _ in range(6):
        child, encoded = fan(child, 0, 174)
        blocks[child] = encoded
    root = child
    assert file_size(root, blocks.__getitem__) == 0
    assert len(car_blocks(root, blocks)) == 7
    message = f"{root} takes more than {visit_budget(0)} blocks for its first 0 bytes"
    for read in (
        lambda: b"".join(read_file(root, blocks.__getitem__)),
        lambda: assemble_file(root, iter(car_blocks(root, blocks)), io.BytesIO(), lambda _: None),
    ):
        with pytest.raises(UnixfsError, match=message):
            read()


def test_bytes_behind_a_long_chain_repeated_are_refused_after_the_visit_budget() -> None:
    """One byte 1,000 blocks deep, linked 174 x 174 times: 30 million visits for 30 KB.

    Read whole, or from byte 100 (a range meets as many repeats per byte), or as the blocks
    of a CAR of a byte range.
    """
    chained, blocks = chain(1000, b"!")
    middle, middle_block = fan(chained, 1, 174)
    root, root_block = fan(middle, 174, 174)
    blocks |= {middle: middle_block, root: root_block}
    assert file_size(root, blocks.__getitem__) == 174 * 174
    for read in (
        lambda: b"".join(read_file(root, blocks.__getitem__)),
        lambda: assemble_file(root, iter(car_blocks(root, blocks)), io.BytesIO(), lambda _: None),
        lambda: b"".join(read_file(root, blocks.__getitem__, 100, 1000)),
        lambda: list(file_range_blocks(root, blocks.__getitem__, 100, 1100)),
        lambda: list(file_range_blocks(root, blocks.__getitem__, 100, None)),
    ):
        with pytest.raises(UnixfsError, match=f"{root} takes more than .* blocks for its first"):
            read()


def test_a_range_car_holds_the_blocks_the_reader_visits_and_refuses_what_it_refuses() -> None:
    """Ranges of an honest chain give its blocks in CAR order; one deeper than the limit fails."""
    root, blocks = chain(MAX_DAG_DEPTH)
    covering = [block.cid for block in file_range_blocks(root, blocks.__getitem__, 2, 5)]
    assert covering == [block.cid for block in car_blocks(root, blocks)]
    assert [block.cid for block in file_range_blocks(root, blocks.__getitem__, 3, 3)] == [root]
    deeper, deeper_blocks = chain(MAX_DAG_DEPTH + 1)
    with pytest.raises(UnixfsError, match=f"deeper than {MAX_DAG_DEPTH} levels"):
        list(file_range_blocks(deeper, deeper_blocks.__getitem__, 2, 5))


def test_an_imported_file_of_one_byte_chunks_under_two_links_is_within_budget() -> None:
    """The most blocks per byte an importer makes: a leaf per byte, about as many inner nodes."""
    data = bytes(range(256)) * 12
    blocks, root = import_bytes(data, ImportParams(chunk_size=1, max_links=2))
    assert len(blocks) == 2 * len(data)
    store = dict(blocks)
    assert b"".join(read_file(root, store.__getitem__)) == data
    assert b"".join(read_file(root, store.__getitem__, 1000, 1)) == data[1000:1001]
    with io.BytesIO() as out:
        assert assemble_file(root, iter(car_blocks(root, store)), out, lambda _: None) == len(data)


def padded_leaf(junk: int) -> tuple[CID, bytes]:
    """A file node of one byte that also carries ``junk`` bytes in a UnixFS field no reader
    knows (number 15): valid, and skipped, but read and hashed whenever the node is."""
    unixfs = UnixfsData(FILE, b"!", 1).encode() + len_field(15, b"\0" * junk)
    encoded = PBNode([], unixfs).encode()
    return CID.from_block(encoded, DAG_PB, 1), encoded


def padded_file(junk: int, count: int) -> tuple[CID, dict[CID, bytes]]:
    """A file of ``count`` bytes: one root linking ``count`` times to a padded leaf."""
    leaf, leaf_block = padded_leaf(junk)
    root, root_block = fan(leaf, 1, count)
    return root, {leaf: leaf_block, root: root_block}


class Counted:
    """A block getter over ``store`` that counts the bytes it hands out."""

    def __init__(self, store: dict[CID, bytes]) -> None:
        self.store = store
        self.bytes = 0

    def __call__(self, cid: CID) -> bytes:
        block = self.store[cid]
        self.bytes += len(block)
        return block


def test_a_block_carrying_megabytes_beside_its_byte_is_refused_after_the_read_budget() -> None:
    """A leaf of one byte and 1 MiB of junk, linked 64 times: well within two visits per
    byte, but each visit reads and hashes 1 MiB (with 8 MiB, a CAR section's most, ~19 ms
    per byte sent). Every read path stops once the bytes read pass the budget, one block
    over it at most, where it read 64 MiB before."""
    root, blocks = padded_file(1 << 20, 64)
    leaf_size = len(blocks[padded_leaf(1 << 20)[0]])
    assert file_size(root, blocks.__getitem__) == 64
    assert visit_budget(0) > 64  # the block count alone lets its 65 visits through
    message = f"{root} takes more than .* bytes of blocks for its first .* bytes"
    reads: list[Callable[[Counted], object]] = [
        lambda get: b"".join(read_file(root, get)),
        lambda get: b"".join(read_file(root, get, 3, 60)),
        lambda get: list(file_range_blocks(root, get, 3, 63)),
        lambda get: list(file_range_blocks(root, get, 0, None)),
    ]
    for read in reads:
        get = Counted(blocks)
        with pytest.raises(UnixfsError, match=message):
            read(get)
        assert READ_ALLOWANCE < get.bytes <= read_budget(64) + leaf_size
        assert get.bytes < 10 * leaf_size  # of the 64 leaf reads the file asks for


def test_inner_blocks_carrying_megabytes_are_refused_when_a_stream_replays_them() -> None:
    """A CAR carries a repeated block once, so the stream hashes the padded block once; an
    inner node that repeats is decoded again each time, and that is what the budget counts."""
    root, blocks = padded_file(1 << 20, 64)
    assert len(car_blocks(root, blocks)) == 2
    with io.BytesIO() as out:
        assert assemble_file(root, iter(car_blocks(root, blocks)), out, lambda _: None) == 64
    padded_inner = PBNode(
        [Link(CID.from_block(b"!", RAW, 1), "", 1)],
        UnixfsData(FILE, b"", 1, [1]).encode() + len_field(15, b"\0" * (1 << 20)),
    ).encode()
    inner = CID.from_block(padded_inner, DAG_PB, 1)
    top, top_block = fan(inner, 1, 64)
    store = {top: top_block, inner: padded_inner, CID.from_block(b"!", RAW, 1): b"!"}
    with pytest.raises(UnixfsError, match=f"{top} takes more than .* bytes of blocks"):
        assemble_file(top, iter(car_blocks(top, store)), io.BytesIO(), lambda _: None)


@pytest.mark.parametrize(
    "params",
    [
        ImportParams.from_options(),
        ImportParams.from_options(profile="unixfs-v1-2025"),
        ImportParams(chunk_size=4096, max_links=16),
        ImportParams(cid_version=0, raw_leaves=False, chunk_size=1000, max_links=174),
    ],
    ids=["kubo-v0", "v1-2025", "4k-16-links", "1000-bytes-dag-pb-leaves"],
)
def test_an_honest_file_of_several_mib_reads_whole_and_in_ranges(params: ImportParams) -> None:
    """An importer's blocks hold its content and a little protobuf: whole reads take 1.0x to
    1.06x, far inside the budget; a one-byte range takes the paths to it, within the
    allowance."""
    data = bytes(range(256)) * (6 * 4096) + b"tail"  # 6 MiB and 4 bytes
    blocks, root = import_bytes(data, params)
    store = dict(blocks)
    get = Counted(store)
    assert b"".join(read_file(root, get)) == data
    assert len(data) <= get.bytes <= 1.06 * len(data)
    with io.BytesIO() as out:
        assert assemble_file(root, iter(car_blocks(root, store)), out, lambda _: None) == len(data)
    for offset in (0, params.chunk_size - 1, len(data) // 2, len(data) - 1):
        get = Counted(store)
        assert b"".join(read_file(root, get, offset, 2)) == data[offset : offset + 2]
        assert get.bytes <= READ_ALLOWANCE
        covering = list(file_range_blocks(root, store.__getitem__, offset, offset + 2))
        assert len(covering) <= 2 * 4


def test_one_byte_chunks_beyond_the_allowance_read_within_the_factor() -> None:
    """The most bytes of blocks per byte an importer makes: a leaf and a two-link node per
    byte, about 104x; 84 KiB of them take 9 MB, past the allowance, within the factor."""
    data = bytes(range(256)) * 336
    blocks, root = import_bytes(data, ImportParams(cid_version=0, chunk_size=1, max_links=2))
    store = dict(blocks)
    get = Counted(store)
    assert b"".join(read_file(root, get)) == data
    assert READ_ALLOWANCE < get.bytes < READ_FACTOR // 2 * len(data)
    with io.BytesIO() as out:
        assert assemble_file(root, iter(car_blocks(root, store)), out, lambda _: None) == len(data)


def test_every_file_of_the_ipfs_fixtures_reads_within_both_budgets() -> None:
    """Each file node of the gateway conformance CARs (HAMT directories' files among them)
    whose blocks the CAR holds reads whole."""
    read = 0
    for path in sorted(car_path("car").rglob("*.car")):
        with path.open("rb") as stream:
            store = {block.cid: block.data for block in CarReader(stream)}
        for cid, block in store.items():
            if cid.codec != DAG_PB or PBNode.decode(block).data is None:
                continue
            if UnixfsData.decode(PBNode.decode(block).data or b"").type != FILE:
                continue
            if any(link not in store for link, _ in walk_links(cid, store)):
                continue
            content = b"".join(read_file(cid, store.__getitem__))
            assert len(content) == file_size(cid, store.__getitem__)
            read += 1
    assert read >= 10


def walk_links(root: CID, store: dict[CID, bytes]) -> list[tuple[CID, CID]]:
    """Every (child, parent) link under ``root`` among the blocks ``store`` holds."""
    found: list[tuple[CID, CID]] = []
    stack = [root]
    while stack:
        cid = stack.pop()
        if cid.codec != DAG_PB or cid not in store:
            continue
        for link in PBNode.decode(store[cid]).links:
            found.append((link.cid, cid))
            stack.append(link.cid)
    return found


def test_a_walk_cut_short_takes_back_the_blocks_it_did_not_finish() -> None:
    """A ``seen`` shared by several roots' walks lets a sub-DAG they share be read once; a
    walk that stopped at a missing block must not leave the blocks above it there, or the
    next root over them would pass for complete."""
    gone = CID.from_block(b"gone", RAW, 1)
    here = CID.from_block(b"here", RAW, 1)
    middle_data = PBNode([Link(here, "a", 4), Link(gone, "b", 4)], None).encode()
    middle = CID.from_block(middle_data, DAG_PB, 1)
    first_data = PBNode([Link(middle, "m", 8)], b"first").encode()
    second_data = PBNode([Link(middle, "m", 8)], b"second").encode()
    first = CID.from_block(first_data, DAG_PB, 1)
    second = CID.from_block(second_data, DAG_PB, 1)
    store = {here: b"here", middle: middle_data, first: first_data, second: second_data}
    seen: set[CID] = set()
    with pytest.raises(KeyError):
        list(walk_dag(first, store.__getitem__, "all", seen))
    assert seen == {here}
    with pytest.raises(KeyError):
        list(walk_dag(second, store.__getitem__, "all", seen))
    store[gone] = b"gone"
    assert [block.cid for block in walk_dag(second, store.__getitem__, "all", seen)] == [
        second,
        middle,
        gone,
    ]
    assert seen == {here, gone, middle, second}
