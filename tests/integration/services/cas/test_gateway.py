"""The trustless gateway: file bytes, ranges, raw blocks and CARs a client can verify."""

from __future__ import annotations

import io

import httpx
import pytest

from robocloud.car import CarReader
from robocloud.cas import Cas
from robocloud.cid import CID
from robocloud.unixfs import ImportParams, import_bytes
from tests.procs import ServiceProcess


@pytest.fixture(scope="module")
def cas_service(shared_cas_service: ServiceProcess) -> ServiceProcess:
    """This module's tests share one cas: none of them needs an empty store."""
    return shared_cas_service


DATA = bytes(range(251)) * 5000  # 1,255,000 bytes: five leaves under one root
RAW = "application/vnd.ipld.raw"
CAR = "application/vnd.ipld.car"


@pytest.fixture
def stored(cas: Cas) -> CID:
    return cas.add_bytes(DATA)


def get(service: ServiceProcess, cid: CID | str, **kwargs: object) -> httpx.Response:
    return httpx.get(f"{service.url}/ipfs/{cid}", timeout=30, **kwargs)  # type: ignore[arg-type]


def test_file_bytes_with_etag_and_length(cas_service: ServiceProcess, stored: CID) -> None:
    response = get(cas_service, stored)
    assert response.status_code == 200
    assert response.content == DATA
    assert response.headers["etag"] == f'"{stored}"'
    assert response.headers["content-length"] == str(len(DATA))
    assert response.headers["accept-ranges"] == "bytes"
    assert "immutable" in response.headers["cache-control"]
    assert response.headers["x-ipfs-path"] == f"/ipfs/{stored}"


def test_head_has_the_headers_and_no_body(cas_service: ServiceProcess, stored: CID) -> None:
    response = httpx.head(f"{cas_service.url}/ipfs/{stored}")
    assert response.status_code == 200
    assert response.headers["content-length"] == str(len(DATA))
    assert response.content == b""


def test_if_none_match_is_304(cas_service: ServiceProcess, stored: CID) -> None:
    response = get(cas_service, stored, headers={"If-None-Match": f'"{stored}"'})
    assert response.status_code == 304
    assert response.content == b""


@pytest.mark.parametrize(
    ("header", "start", "end"),
    [
        ("bytes=0-0", 0, 1),
        ("bytes=262140-262150", 262140, 262151),
        ("bytes=1000000-", 1000000, len(DATA)),
        ("bytes=-10", len(DATA) - 10, len(DATA)),
        ("bytes=1254990-9999999", 1254990, len(DATA)),
    ],
)
def test_range_is_206(
    cas_service: ServiceProcess, stored: CID, header: str, start: int, end: int
) -> None:
    response = get(cas_service, stored, headers={"Range": header})
    assert response.status_code == 206
    assert response.content == DATA[start:end]
    assert response.headers["content-range"] == f"bytes {start}-{end - 1}/{len(DATA)}"
    assert response.headers["content-length"] == str(end - start)


def test_several_ranges_get_the_whole_file(cas_service: ServiceProcess, stored: CID) -> None:
    response = get(cas_service, stored, headers={"Range": "bytes=0-1,5-6"})
    assert response.status_code == 200
    assert response.content == DATA


@pytest.mark.parametrize("header", ["bytes=1255000-", "bytes=9999999-10000000", "bytes=-0"])
def test_range_outside_the_file_is_416(
    cas_service: ServiceProcess, stored: CID, header: str
) -> None:
    response = get(cas_service, stored, headers={"Range": header})
    assert response.status_code == 416
    assert response.headers["content-range"] == f"bytes */{len(DATA)}"
    error = response.json()["error"]
    assert error["code"] == "range_not_satisfiable"
    assert error["details"] == {"header": "Range", "size": len(DATA)}


@pytest.mark.parametrize(
    "how", [{"params": {"format": "raw"}}, {"headers": {"Accept": RAW}}], ids=["param", "accept"]
)
def test_raw_block(cas_service: ServiceProcess, stored: CID, how: dict) -> None:
    response = get(cas_service, stored, **how)
    assert response.status_code == 200
    assert response.headers["content-type"] == RAW
    stored.verify(response.content)
    assert response.headers["etag"] == f'"{stored}.raw"'


@pytest.mark.parametrize(("scope", "count"), [("block", 1), ("entity", 6), ("all", 6)])
def test_car_scopes(cas_service: ServiceProcess, stored: CID, scope: str, count: int) -> None:
    response = get(cas_service, stored, params={"format": "car", "dag-scope": scope})
    assert response.status_code == 200
    assert response.headers["content-type"].startswith(CAR)
    reader = CarReader(io.BytesIO(response.content))
    assert reader.roots == [stored]
    blocks = list(reader)  # every block verified against its CID by the reader
    assert len(blocks) == count
    expected, _ = import_bytes(DATA, ImportParams())
    assert {block.cid for block in blocks} <= {block.cid for block in expected}


def test_car_by_accept_header(cas_service: ServiceProcess, stored: CID) -> None:
    response = get(cas_service, stored, headers={"Accept": f"{CAR}; version=1"})
    assert response.headers["content-type"].startswith(CAR)
    assert CarReader(io.BytesIO(response.content)).roots == [stored]


def test_unknown_format_and_scope_are_400(cas_service: ServiceProcess, stored: CID) -> None:
    response = get(cas_service, stored, params={"format": "tar"})
    assert response.status_code == 400
    assert response.json()["error"]["details"] == {"field": "format"}
    response = get(cas_service, stored, params={"format": "car", "dag-scope": "most"})
    assert response.status_code == 400
    assert response.json()["error"]["code"] == "invalid_dag_scope"


def test_empty_file(cas: Cas, cas_service: ServiceProcess) -> None:
    cid = cas.add_bytes(b"")
    response = get(cas_service, cid)
    assert response.status_code == 200
    assert response.content == b""
    assert response.headers["content-length"] == "0"


def test_only_if_cached_miss_is_412(cas_service: ServiceProcess) -> None:
    missing = CID.from_block(b"nobody stored this")
    response = get(cas_service, missing, headers={"Cache-Control": "only-if-cached"})
    assert response.status_code == 412
    assert response.json()["error"]["details"] == {"cid": str(missing)}
