"""DAGs deeper than any importer makes, or repeating a chain to no end: refused with the limit
named, the service unhurt.

A 30,000-deep dag-pb chain (a 2.6 MB CAR) used to segfault cas when it was read back: the
reader recursed once per level, and py_ecc had raised the recursion limit to 100,000.
"""

from __future__ import annotations

import io

import httpx
import pytest

from robocloud.car import CarReader, write_car
from robocloud.cid import CID, DAG_PB, Block
from robocloud.client import ServiceClient
from robocloud.dagpb import Link, PBNode
from robocloud.errors import ApiError
from robocloud.unixfs import FILE, MAX_DAG_DEPTH, UnixfsData
from tests.integration.services.cas.conftest import error_of, multipart, store_unchanged
from tests.procs import ServiceProcess
from tests.unit.robocloud.test_directory import repeating_hamt
from tests.unit.robocloud.test_unixfs import LEAF, chain, fan


@pytest.fixture(scope="module")
def cas_service(shared_cas_service: ServiceProcess) -> ServiceProcess:
    """This module's tests share one cas: none of them needs an empty store."""
    return shared_cas_service


def import_car(signed: ServiceClient, root: CID, blocks: dict[CID, bytes]) -> None:
    car = b"".join(write_car([root], [Block(cid, data) for cid, data in blocks.items()]))
    body, content_type = multipart(("chain.car", car))
    signed.request(
        "POST", "/api/v0/dag/import", content=body, headers={"Content-Type": content_type}
    )


def alive(service: ServiceProcess) -> bool:
    assert service.process is not None
    return service.process.poll() is None and httpx.get(f"{service.url}/healthz").is_success


def test_a_30000_deep_car_is_refused_whole(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    root, blocks = chain(30_000)
    with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
        import_car(signed, root, blocks)
    error = error_of(exc, 400, "invalid_dag")
    assert f"deeper than {MAX_DAG_DEPTH} levels" in error.message
    assert httpx.get(f"{cas_service.url}/ipfs/{root}").status_code == 404
    assert alive(cas_service)


def test_a_too_deep_dag_put_block_by_block_is_refused_when_read(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """Blocks stored one by one are each valid; reading the file is what must stop."""
    root, blocks = chain(MAX_DAG_DEPTH + 5)
    leaf_and_nodes = list(blocks.values())
    raw_leaf, nodes = leaf_and_nodes[0], leaf_and_nodes[1:]
    assert raw_leaf == LEAF
    for codec, parts in (("raw", [raw_leaf]), ("dag-pb", nodes)):
        body, content_type = multipart(*((str(i), data) for i, data in enumerate(parts)))
        signed.request(
            "POST",
            "/api/v0/block/put",
            params={"cid-codec": codec},
            content=body,
            headers={"Content-Type": content_type},
        )
    for request in (
        httpx.Request("GET", f"{cas_service.url}/ipfs/{root}"),
        httpx.Request("GET", f"{cas_service.url}/ipfs/{root}?format=car"),
        httpx.Request("GET", f"{cas_service.url}/ipfs/{root}?format=car&entity-bytes=2:5"),
        httpx.Request("POST", f"{cas_service.url}/api/v0/cat?arg={root}"),
        httpx.Request("POST", f"{cas_service.url}/api/v0/dag/export?arg={root}"),
    ):
        with httpx.Client(timeout=60) as client:
            response = client.send(request)
        assert response.status_code == 400, (request.url, response.text[:300])
        assert f"deeper than {MAX_DAG_DEPTH} levels" in response.json()["error"]["message"]
    with pytest.raises(ApiError) as exc:
        signed.request("POST", "/api/v0/pin/add", params={"arg": str(root)})
    assert f"deeper than {MAX_DAG_DEPTH} levels" in error_of(exc, 400, "invalid_dag").message
    assert alive(cas_service)


def lying_file() -> tuple[CID, dict[CID, bytes], int]:
    """Two honest 4 MiB leaves, then one that holds 5 bytes where its root declares 10."""
    leaves = [bytes([1]) * (4 << 20), bytes([2]) * (4 << 20), b"short"]
    cids = [CID.from_block(leaf) for leaf in leaves]
    sizes = [len(leaves[0]), len(leaves[1]), 10]
    unixfs = UnixfsData(FILE, b"", sum(sizes), sizes)
    root_block = PBNode([Link(c, "", s) for c, s in zip(cids, sizes, strict=True)], unixfs.encode())
    encoded = root_block.encode()
    root = CID.from_block(encoded, DAG_PB)
    return root, {root: encoded, **dict(zip(cids, leaves, strict=True))}, sum(sizes)


def test_a_file_shorter_than_its_root_declares_is_cut_off_not_completed(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    root, blocks, declared = lying_file()
    import_car(signed, root, blocks)
    url = f"{cas_service.url}/ipfs/{root}"
    received: list[bytes] = []

    def read_all(response: httpx.Response) -> None:
        received.extend(response.iter_bytes())

    with httpx.stream("GET", url, timeout=60) as response:
        assert response.status_code == 200
        assert response.headers["content-length"] == str(declared)
        with pytest.raises(httpx.RemoteProtocolError):
            read_all(response)
    assert sum(map(len, received)) < declared
    tail = httpx.get(url, headers={"Range": f"bytes={8 << 20}-"}, timeout=60)
    assert tail.status_code == 400
    assert "holds 5 bytes but its parent" in tail.json()["error"]["message"]
    assert alive(cas_service)


def test_a_dag_repeating_a_long_chain_is_refused_for_ranges_within_the_visit_budget(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """1,003 blocks that stand for 30,276 bytes, each behind 1,002 levels: a byte range read
    or a CAR of a byte range stops at the visit budget, named, and the service stays up."""
    chained, blocks = chain(1000, b"!")
    middle, middle_block = fan(chained, 1, 174)
    root, root_block = fan(middle, 174, 174)
    blocks |= {middle: middle_block, root: root_block}
    import_car(signed, root, blocks)
    whole_car = httpx.get(f"{cas_service.url}/ipfs/{root}?format=car", timeout=60)
    assert whole_car.status_code == 200
    assert {block.cid for block in CarReader(io.BytesIO(whole_car.content))} == set(blocks)
    for request, code in (
        (
            httpx.Request("GET", f"{cas_service.url}/ipfs/{root}", headers={"Range": "bytes=100-"}),
            "not_a_file",
        ),
        (
            httpx.Request("GET", f"{cas_service.url}/ipfs/{root}?format=car&entity-bytes=100:*"),
            "invalid_dag",
        ),
    ):
        with httpx.Client(timeout=60) as client:
            response = client.send(request)
        assert response.status_code == 400, (request.url, response.text[:300])
        error = response.json()["error"]
        assert error["code"] == code
        assert error["details"]["cid"] == str(root)
        assert f"{root} takes more than" in error["message"]
    assert alive(cas_service)


def test_a_hamt_whose_shards_repeat_one_sub_shard_is_refused_when_listed(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """Listing it used to build 16.7 M entries (the service passed 700 MB in 14 s)."""
    root, blocks = repeating_hamt(3)
    import_car(signed, root, blocks)
    bottom_shard = list(blocks)[1]  # the walk goes down to it, then meets it again
    for request in (
        httpx.Request("GET", f"{cas_service.url}/ipfs/{root}/", headers={"Accept": "text/html"}),
        httpx.Request("POST", f"{cas_service.url}/api/v0/ls?arg={root}"),
    ):
        with httpx.Client(timeout=60) as client:
            response = client.send(request)
        assert response.status_code == 400, (request.url, response.text[:300])
        error = response.json()["error"]
        assert error["code"] == "invalid_dag"
        assert error["details"]["cid"] == str(root)
        assert f"links the shard {bottom_shard} twice" in error["message"]
    assert alive(cas_service)
