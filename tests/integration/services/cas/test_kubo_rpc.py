"""The kubo RPC subset end to end: the answers kubo gives, the CIDs kubo computes."""

from __future__ import annotations

import io
import json
from typing import Any

import httpx
import pytest

import robocloud
from robocloud.car import CarReader, write_car
from robocloud.cas import Cas
from robocloud.cid import CID, DAG_PB, RAW, Block
from robocloud.client import ServiceClient
from robocloud.dagpb import PBNode
from robocloud.errors import ApiError
from robocloud.unixfs import ImportParams, import_bytes
from tests.integration.services.cas.conftest import (
    error_of,
    multipart,
    pin_list,
    post_files,
    repo_stat,
    store_unchanged,
)
from tests.procs import ServiceProcess
from tests.unit.robocloud.ipfs_vectors import PROFILES, car_path, input_named, vectors


@pytest.fixture(scope="module")
def cas_service(shared_cas_service: ServiceProcess) -> ServiceProcess:
    """This module's tests share one cas: none of them needs an empty store."""
    return shared_cas_service


HELLO = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"
SERVICE_VECTORS = [
    "hello_world.txt",
    "empty.bin",
    "chacha20_chunk-v0-seed_262144.bin",
    "chacha20_chunk-v0-seed_262145.bin",
    "chacha20:v0-seed:45613057",
]
"""Through HTTP: the empty file, one chunk, one chunk plus a byte, and 175 chunks (a two-level
tree); the SDK's unit tests run all 46 shared vectors through the same importer."""


def expected_cid(name: str, profile: str) -> str:
    for vector in vectors()["vectors"]:
        if vector["input"] == name:
            for expected in vector["expected"]:
                if expected["profile"] == profile:
                    return str(expected["cid"])
    raise KeyError((name, profile))


def add_lines(client: ServiceClient, body: bytes, content_type: str, **params: object) -> list[Any]:
    response = client.request(
        "POST", "/api/v0/add", params=params, content=body, headers={"Content-Type": content_type}
    )
    assert response.headers["x-chunked-output"] == "1"
    return [json.loads(line) for line in response.text.splitlines()]


def test_hello_world_gets_kubos_cid(signed: ServiceClient) -> None:
    body, content_type = multipart(("hello.txt", b"Hello world"))
    lines = add_lines(signed, body, content_type, **{"cid-version": 1})
    assert lines == [{"Name": "hello.txt", "Hash": HELLO, "Size": "11"}]


@pytest.mark.parametrize("name", SERVICE_VECTORS)
@pytest.mark.parametrize("profile", ["v0", "v1-raw-256k"])
def test_vectors_through_the_service(signed: ServiceClient, name: str, profile: str) -> None:
    data = input_named(name)
    params = PROFILES[profile]
    body, content_type = multipart(("f", data))
    lines = add_lines(
        signed,
        body,
        content_type,
        **{"cid-version": params.cid_version, "raw-leaves": str(params.raw_leaves).lower()},
    )
    assert lines[-1]["Hash"] == expected_cid(name, profile)
    got = signed.request("POST", "/api/v0/cat", params={"arg": lines[-1]["Hash"]}, signed=False)
    assert got.content == data


def test_cumulative_size_is_the_dag_size(signed: ServiceClient) -> None:
    data = input_named("chacha20_chunk-v0-seed_262145.bin")
    blocks, root = import_bytes(data)
    body, content_type = multipart(("f", data))
    [line] = add_lines(signed, body, content_type, **{"cid-version": 1})
    assert line["Hash"] == str(root)
    assert int(line["Size"]) == sum(len(block.data) for block in blocks)


def test_several_files_and_chunker_and_profile(signed: ServiceClient) -> None:
    body, content_type = multipart(("a", b"a" * 5000), ("b", b"b" * 10))
    lines = add_lines(signed, body, content_type, chunker="size-1024", **{"cid-version": 1})
    small = ImportParams(chunk_size=1024)
    assert [line["Name"] for line in lines] == ["a", "b"]
    assert lines[0]["Hash"] == str(import_bytes(b"a" * 5000, small)[1])
    data = input_named("chacha20_chunk-v1-seed_1048577.bin")
    body, content_type = multipart(("c", data))
    [line] = add_lines(signed, body, content_type, profile="unixfs-v1-2025")
    assert line["Hash"] == expected_cid("chacha20_chunk-v1-seed_1048577.bin", "v1-2025")


def test_only_hash_stores_nothing(signed: ServiceClient, cas_service: ServiceProcess) -> None:
    body, content_type = multipart(("hello.txt", b"Hello world, only hashed"))
    with store_unchanged(cas_service):
        [line] = add_lines(signed, body, content_type, **{"cid-version": 1, "only-hash": "true"})
    assert line["Hash"] == str(CID.from_block(b"Hello world, only hashed"))


def test_cat_offset_and_length(cas: Cas, signed: ServiceClient) -> None:
    data = bytes(range(256)) * 4096
    cid = cas.add_bytes(data)

    def cat(**params: int) -> bytes:
        arguments = {"arg": str(cid), **params}
        return signed.request("POST", "/api/v0/cat", params=arguments, signed=False).content

    assert cat(offset=262_000, length=5_000) == data[262_000:267_000]
    assert cat(offset=len(data) - 3) == data[-3:]
    assert cat(offset=len(data) + 10) == b""


def test_block_put_get_stat(signed: ServiceClient, cas_service: ServiceProcess) -> None:
    body, content_type = multipart(("b1", b"block one"), ("b2", b"block two"))
    response = signed.request(
        "POST", "/api/v0/block/put", content=body, headers={"Content-Type": content_type}
    )
    keys = [json.loads(line) for line in response.text.splitlines()]
    one = CID.from_block(b"block one", RAW)
    assert keys == [
        {"Key": str(one), "Size": 9},
        {"Key": str(CID.from_block(b"block two", RAW)), "Size": 9},
    ]
    url = cas_service.url
    assert httpx.post(f"{url}/api/v0/block/get", params={"arg": str(one)}).content == b"block one"
    stat = httpx.post(f"{url}/api/v0/block/stat", params={"arg": str(one)}).json()
    assert stat == {"Key": str(one), "Size": 9}


def test_block_put_of_many_parts_is_one_pack(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """10,000 parts once wrote 20,000 files (26 s); they are one staged pack, like an add."""
    blocks = [f"block {i}".encode() for i in range(2_000)]
    body, content_type = multipart(*((f"b{i}", data) for i, data in enumerate(blocks)))
    packs = set((cas_service.data_dir / "packs").glob("*"))
    stored = repo_stat(cas_service.url)["NumObjects"]
    response = signed.request(
        "POST", "/api/v0/block/put", content=body, headers={"Content-Type": content_type}
    )
    keys = [json.loads(line)["Key"] for line in response.text.splitlines()]
    assert keys == [str(CID.from_block(data, RAW)) for data in blocks]
    added = set((cas_service.data_dir / "packs").glob("*")) - packs
    assert sorted(path.suffix for path in added) == [".idx", ".pack"]
    assert repo_stat(cas_service.url)["NumObjects"] == stored + 2_000
    last = httpx.post(f"{cas_service.url}/api/v0/block/get", params={"arg": keys[-1]})
    assert last.content == blocks[-1]


def test_block_put_with_one_bad_part_stores_none(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    good = PBNode([], b"\x08\x02").encode()
    body, content_type = multipart(("good", good), ("bad", b"\xff\xff not protobuf"))
    with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
        signed.request(
            "POST",
            "/api/v0/block/put",
            params={"cid-codec": "dag-pb"},
            content=body,
            headers={"Content-Type": content_type},
        )
    assert "block 1" in error_of(exc, 400, "invalid_block").message


def test_block_put_dag_pb_must_decode(signed: ServiceClient, cas_service: ServiceProcess) -> None:
    body, content_type = multipart(("b", b"\xff\xff not protobuf"))
    response = httpx.post(
        f"{cas_service.url}/api/v0/block/put",
        params={"cid-codec": "dag-pb"},
        content=body,
        headers={"Content-Type": content_type},
    )
    assert response.status_code == 401  # unsigned first
    with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
        signed.request(
            "POST",
            "/api/v0/block/put",
            params={"cid-codec": "dag-pb"},
            content=body,
            headers={"Content-Type": content_type},
        )
    error_of(exc, 400, "invalid_block")


def test_dag_export_is_a_verifiable_car(cas: Cas, cas_service: ServiceProcess) -> None:
    data = bytes(700_000)
    cid = cas.add_bytes(data)
    response = httpx.post(f"{cas_service.url}/api/v0/dag/export", params={"arg": str(cid)})
    reader = CarReader(io.BytesIO(response.content))
    assert reader.roots == [cid]
    blocks = list(reader)
    assert blocks[0].cid == cid
    assert blocks[0].cid.codec == DAG_PB
    assert len(blocks) == 3  # the root, a full zero chunk (stored once), the tail chunk


@pytest.mark.parametrize(
    "fixture", vectors()["cars"][:4], ids=lambda c: str(c["path"]).rsplit("/", 1)[-1]
)
def test_dag_import_of_conformance_cars(
    signed: ServiceClient, cas_service: ServiceProcess, fixture: dict[str, Any]
) -> None:
    raw = car_path(str(fixture["path"])).read_bytes()
    roots = CarReader(io.BytesIO(raw)).roots
    body, content_type = multipart(("fixture.car", raw))
    response = signed.request(
        "POST", "/api/v0/dag/import", content=body, headers={"Content-Type": content_type}
    )
    answers = [json.loads(line) for line in response.text.splitlines()]
    assert [answer["Root"]["Cid"]["/"] for answer in answers] == [str(root) for root in roots]
    exported = httpx.post(f"{cas_service.url}/api/v0/dag/export", params={"arg": str(roots[0])})
    assert {b.cid for b in CarReader(io.BytesIO(exported.content))} <= {
        b.cid for b in CarReader(io.BytesIO(raw))
    }


def test_dag_import_round_trip_pins_roots(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    blocks, root = import_bytes(bytes(range(200)) * 3000, ImportParams(chunk_size=65536))
    car = b"".join(write_car([root], blocks))
    body, content_type = multipart(("x.car", car))
    response = signed.request(
        "POST", "/api/v0/dag/import", content=body, headers={"Content-Type": content_type}
    )
    assert json.loads(response.text) == {"Root": {"Cid": {"/": str(root)}, "PinErrorMsg": ""}}
    pins = httpx.post(f"{cas_service.url}/api/v0/pin/ls").json()["Keys"]
    assert pins[str(root)]["Owners"] == [signed.identity.address]  # type: ignore[union-attr]


def import_cars(signed: ServiceClient, *cars: bytes) -> httpx.Response:
    body, content_type = multipart(*((f"{index}.car", car) for index, car in enumerate(cars)))
    return signed.request(
        "POST", "/api/v0/dag/import", content=body, headers={"Content-Type": content_type}
    )


def test_dag_import_answers_a_root_named_by_two_cars_once(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """kubo keeps the roots of all parts in one set; each is walked, pinned and answered
    once, in the order first named."""
    blocks, root = import_bytes(b"named twice" * 100, ImportParams())
    other = Block(CID.from_block(b"named once"), b"named once")
    first = b"".join(write_car([root], blocks))
    second = b"".join(write_car([root, other.cid], [*blocks, other]))
    response = import_cars(signed, first, second)
    answers = [json.loads(line)["Root"] for line in response.text.splitlines()]
    assert answers == [
        {"Cid": {"/": str(root)}, "PinErrorMsg": ""},
        {"Cid": {"/": str(other.cid)}, "PinErrorMsg": ""},
    ]
    assert {str(root), str(other.cid)} <= pin_list(cas_service.url)["Keys"].keys()


def test_dag_import_stats_count_every_block_section_read_as_kubo(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """kubo's ``dag import --stats`` adds a last line counting the block sections it read,
    one sent twice counted twice; without pinning it answers that line alone."""
    blocks, root = import_bytes(bytes(range(256)) * 2000, ImportParams(chunk_size=65536))
    car = b"".join(write_car([root], blocks))
    size = sum(len(block.data) for block in blocks)
    response = post_files(signed, "/api/v0/dag/import?stats=true", ("0.car", car), ("1.car", car))
    assert [json.loads(line) for line in response.text.splitlines()] == [
        {"Root": {"Cid": {"/": str(root)}, "PinErrorMsg": ""}},
        {"Stats": {"BlockCount": 2 * len(blocks), "BlockBytesCount": 2 * size}},
    ]
    response = post_files(signed, "/api/v0/dag/import?stats=true&pin-roots=false", ("0.car", car))
    assert [json.loads(line) for line in response.text.splitlines()] == [
        {"Stats": {"BlockCount": len(blocks), "BlockBytesCount": size}}
    ]


def test_dag_import_of_more_roots_than_a_header_holds_over_its_cars_stores_nothing(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """Each header holds at most 1,024 roots, but the parts had no bound together: 400 CARs
    of 1,024 roots were 409,600 roots walked, pinned and answered (488 MiB, a 103 MiB
    answer). The distinct roots of one import are bounded as one header's are."""
    leaves = [Block(CID.from_block(data), data) for data in (b"root %d" % i for i in range(1025))]
    first = b"".join(write_car([leaf.cid for leaf in leaves[:1024]], leaves[:1024]))
    again = b"".join(write_car([leaves[0].cid], leaves[:1]))
    second = b"".join(write_car([leaves[1024].cid], leaves[1024:]))
    with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
        import_cars(signed, first, again, second)
    details = error_of(exc, 400, "too_many_roots").details
    assert details == {"field": "roots", "count": 1025, "limit": 1024}


def test_version_answers_like_kubo(cas_service: ServiceProcess) -> None:
    answer = httpx.post(f"{cas_service.url}/api/v0/version").json()
    assert answer["System"] == "robocloud-cas"
    assert answer["Version"] == robocloud.__version__


def test_a_kubo_method_cas_does_not_offer_is_not_found_not_a_missing_signature(
    cas_service: ServiceProcess,
) -> None:
    """``ipfs id`` against cas was told "header X-Robocloud-Address is required", as if a
    signature would make it work: a request no route takes is answered for what it is."""
    for method, path, status, code in [
        ("POST", "/api/v0/id", 404, "not_found"),
        ("POST", "/api/v0/swarm/peers", 404, "not_found"),
        ("DELETE", "/api/v0/add", 405, "method_not_allowed"),
        (
            "PUT",
            "/ipfs/bafkreicysg23kiwv34eg2d7qweipxwosdo2py4ldv42nbauguluen5v6am",
            405,
            "method_not_allowed",
        ),
    ]:
        answer = httpx.request(method, f"{cas_service.url}{path}")
        error = answer.json()["error"]
        assert (answer.status_code, error["code"]) == (status, code), path
        if status == 404:
            assert error["message"] == f"no route {method} {path}"
    refused = httpx.post(f"{cas_service.url}/api/v0/add", files={"file": b"hello"})
    assert refused.status_code == 401
    assert refused.json()["error"]["code"] == "missing_signature_header"
