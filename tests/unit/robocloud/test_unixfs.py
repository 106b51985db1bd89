"""The importer against IPFS's own vectors, the reader, ranges and the DAG walk."""

from __future__ import annotations

import io

import pytest

from robocloud.car import CarReader
from robocloud.cid import CID, DAG_PB, RAW, Block
from robocloud.unixfs import (
    Importer,
    ImportParams,
    UnixfsError,
    file_size,
    import_bytes,
    list_directory,
    parse_chunker,
    read_file,
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
    from robocloud.dagpb import PBNode

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
    reader = CarReader(
        car_path("car/gateway-conformance/subdir-with-mixed-block-files.car").open("rb")
    )
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
    reader = CarReader(car_path(directory["car"]).open("rb"))
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
    reader = CarReader(car_path("car/gateway-conformance/tooling-car-dag.car").open("rb"))
    store = {block.cid: block.data for block in reader}
    with pytest.raises(UnixfsError, match="not a file"):
        list(read_file(reader.roots[0], store.__getitem__))


def test_car_of_an_import_reads_back() -> None:
    from robocloud.car import write_car

    blocks, root = import_bytes(b"z" * 600_000)
    car = b"".join(write_car([root], walk_dag(root, dict(blocks).__getitem__)))
    reader = CarReader(io.BytesIO(car))
    store = {block.cid: block.data for block in reader}
    assert reader.roots == [root]
    assert b"".join(read_file(root, store.__getitem__)) == b"z" * 600_000
