"""Gateway answers for entry names and parameters a stranger chooses.

Names are any UTF-8 (CJK, ``?``, ``#``, ``%``, CR/LF) and ``dag-scope`` and ``entity-bytes``
any text: each reaches a header or a route, so each must come back percent-encoded or be
refused 400, never a 500, a dropped connection, a broken redirect or a 404 for a name that
exists.
"""

from __future__ import annotations

import io
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx
import pytest

from robocloud.car import CarReader, write_car
from robocloud.cid import CID, DAG_PB, RAW, Block
from robocloud.client import ServiceClient
from robocloud.dagpb import Link, PBNode
from robocloud.identity import Identity
from robocloud.unixfs import DIRECTORY, UnixfsData
from tests.integration.services.cas.conftest import multipart, tree_multipart
from tests.procs import ServiceProcess

CJK = "日本.txt"
INDEX = b"<h1>index</h1>"
ODD_NAMES = ["a?b", "c#d", "50%off", "e%3Ff"]
NEWLINE_NAMES = ["a\nb", "a\r\nX-Evil: 1", "ends\n"]


@pytest.fixture(scope="module")
def cas_service(shared_cas_service: ServiceProcess) -> ServiceProcess:
    return shared_cas_service


@pytest.fixture(scope="module")
def robot(cas_service: ServiceProcess) -> Iterator[ServiceClient]:
    with ServiceClient(cas_service.url, Identity.generate(), retries=0) as client:
        yield client


def raw_block(data: bytes) -> Block:
    return Block(CID.from_block(data, RAW), data)


def directory(entries: dict[str, Block]) -> Block:
    """A plain dag-pb directory of ``entries``, whatever their names."""
    links = [
        Link(block.cid, name, len(block.data))
        for name, block in sorted(entries.items(), key=lambda item: item[0].encode())
    ]
    node = PBNode(links, UnixfsData(DIRECTORY).encode()).encode()
    return Block(CID.from_block(node, DAG_PB), node)


def dag_import(robot: ServiceClient, root: Block, blocks: list[Block]) -> None:
    body, content_type = multipart(("d.car", b"".join(write_car([root.cid], [root, *blocks]))))
    robot.request(
        "POST", "/api/v0/dag/import", content=body, headers={"Content-Type": content_type}
    )


def get(service: ServiceProcess, path: str, **kwargs: Any) -> httpx.Response:
    return httpx.get(f"{service.url}{path}", timeout=30, **kwargs)


def error(response: httpx.Response) -> dict[str, Any]:
    found: dict[str, Any] = response.json()["error"]
    return found


@pytest.fixture(scope="module")
def cjk_root(robot: ServiceClient, tmp_path_factory: pytest.TempPathFactory) -> str:
    """A directory holding ``日本.txt``, added as ``ipfs add -r`` sends it."""
    tree = tmp_path_factory.mktemp("cjk") / "d"
    tree.mkdir()
    (tree / CJK).write_bytes(b"hello")
    body, content_type = tree_multipart(Path(tree))
    response = robot.request(
        "POST",
        "/api/v0/add",
        params={"cid-version": 1},
        content=body,
        headers={"Content-Type": content_type},
    )
    added = {line["Name"]: line["Hash"] for line in map(json.loads, response.text.splitlines())}
    root: str = added["d"]
    return root


@pytest.mark.parametrize("format", [None, "raw", "car"])
def test_a_name_outside_latin_1_is_served_with_its_path_percent_encoded(
    cas_service: ServiceProcess, cjk_root: str, format: str | None
) -> None:
    """``X-Ipfs-Path`` held the decoded name, which Starlette cannot encode: 500 every time."""
    path = f"/ipfs/{cjk_root}/{quote(CJK)}"
    params = {"format": format} if format else {}
    response = get(cas_service, path, params=params)
    assert response.status_code == 200, response.text
    assert response.headers["x-ipfs-path"] == f"/ipfs/{cjk_root}/%E6%97%A5%E6%9C%AC.txt"
    if format == "car":
        blocks = list(CarReader(io.BytesIO(response.content)))
        assert [block.data for block in blocks][-1] == b"hello"
        assert CJK.encode() in blocks[0].data
    else:
        assert response.content == b"hello"
    head = httpx.head(f"{cas_service.url}{path}", params=params, timeout=30)
    assert head.status_code == 200
    assert head.headers["x-ipfs-path"] == response.headers["x-ipfs-path"]


@pytest.fixture(scope="module")
def odd_root(robot: ServiceClient) -> Block:
    """A directory of sites named ``a?b``, ``c#d``, ``50%off`` and ``e%3Ff``."""
    index = raw_block(INDEX)
    site = directory({"index.html": index})
    root = directory(dict.fromkeys(ODD_NAMES, site))
    dag_import(robot, root, [site, index])
    return root


@pytest.mark.parametrize("name", ODD_NAMES)
def test_the_index_html_redirect_leads_back_to_the_same_directory(
    cas_service: ServiceProcess, odd_root: Block, name: str
) -> None:
    """The ``Location`` joined decoded names: ``a?b`` led to ``a`` with a query, ``50%off``
    to ``50`` followed by an escape."""
    encoded = quote(name, safe="")
    redirect = get(cas_service, f"/ipfs/{odd_root.cid}/{encoded}", follow_redirects=False)
    assert redirect.status_code == 301
    assert redirect.headers["location"] == f"/ipfs/{odd_root.cid}/{encoded}/"
    page = get(cas_service, redirect.headers["location"])
    assert (page.status_code, page.content) == (200, INDEX)


@pytest.fixture(scope="module")
def newline_root(robot: ServiceClient) -> Block:
    """A directory whose entries' names hold CR and LF (any UTF-8 is a dag-pb name)."""
    root = directory({name: raw_block(name.encode()) for name in NEWLINE_NAMES})
    dag_import(robot, root, [raw_block(name.encode()) for name in NEWLINE_NAMES])
    return root


@pytest.mark.parametrize("name", NEWLINE_NAMES)
def test_a_name_with_a_newline_is_served(
    cas_service: ServiceProcess, newline_root: Block, name: str
) -> None:
    """The route's ``{path:path}`` did not match ``\\n``: 404 "no route" for an entry that is
    there; the name in the header is encoded, so it cannot add a header of its own."""
    encoded = quote(name, safe="")
    response = get(cas_service, f"/ipfs/{newline_root.cid}/{encoded}")
    assert (response.status_code, response.content) == (200, name.encode())
    assert response.headers["x-ipfs-path"] == f"/ipfs/{newline_root.cid}/{encoded}"
    assert "x-evil" not in response.headers


def test_a_missing_name_with_a_newline_is_path_not_found(
    cas_service: ServiceProcess, newline_root: Block
) -> None:
    response = get(cas_service, f"/ipfs/{newline_root.cid}/nothing%0Ahere")
    assert response.status_code == 404
    assert error(response)["code"] == "path_not_found"
    assert error(response)["details"] == {"segment": "nothing\nhere", "cid": str(newline_root.cid)}


@pytest.mark.parametrize(
    "how",
    [{"params": {"format": "dag-json"}}, {"headers": {"Accept": "application/vnd.ipld.dag-json"}}],
)
def test_dag_json_of_a_block_that_is_not_dag_pb_is_invalid_dag(
    cas_service: ServiceProcess, robot: ServiceClient, how: dict[str, Any]
) -> None:
    """A dag-pb CID whose bytes do not decode was a 500; a CAR of it is 400 ``invalid_dag``."""
    garbage = b"\xff\xff\xffnot dag-pb at all"
    body, content_type = multipart(("block", garbage))
    robot.request("POST", "/api/v0/block/put", content=body, headers={"Content-Type": content_type})
    alias = CID(1, DAG_PB, CID.from_block(garbage, RAW).multihash)
    response = get(cas_service, f"/ipfs/{alias}", **how)
    assert response.status_code == 400
    assert error(response)["code"] == "invalid_dag"
    assert error(response)["details"] == {"cid": str(alias)}
    assert "is not a dag-pb node" in error(response)["message"]
    car = get(cas_service, f"/ipfs/{alias}", params={"format": "car"})
    assert (car.status_code, error(car)["code"]) == (400, error(response)["code"])


@pytest.fixture(scope="module")
def small_directory(robot: ServiceClient) -> Block:
    file = raw_block(b"hello world file")
    root = directory({"f": file})
    dag_import(robot, root, [file])
    return root


@pytest.mark.parametrize("value", ["\r\nX-Evil: 1", "日", "zz", "٣:*", "10:5", "-1:-5", "1:2:3"])
@pytest.mark.parametrize("target", ["", "/f"])
def test_entity_bytes_is_checked_whatever_the_path_names(
    cas_service: ServiceProcess, small_directory: Block, value: str, target: str
) -> None:
    """On a directory the value went unchecked into the ``ETag``: CR/LF dropped the
    connection, non-ASCII was 500 and ``zz`` was ignored."""
    response = get(
        cas_service,
        f"/ipfs/{small_directory.cid}{target}",
        params={"format": "car", "entity-bytes": value},
    )
    assert response.status_code == 400
    assert error(response)["code"] == "invalid_entity_bytes"
    assert error(response)["details"] == {"field": "entity-bytes"}


def test_a_well_formed_entity_bytes_on_a_directory_is_ignored(
    cas_service: ServiceProcess, small_directory: Block
) -> None:
    """As the specification says; the ``ETag`` carries the range in its canonical form."""
    url = f"/ipfs/{small_directory.cid}"
    response = get(cas_service, url, params={"format": "car", "entity-bytes": "0:10"})
    assert response.status_code == 200
    assert [block.cid for block in CarReader(io.BytesIO(response.content))] == [small_directory.cid]
    padded = get(cas_service, url, params={"format": "car", "entity-bytes": "00:010"})
    assert (
        padded.headers["etag"]
        == response.headers["etag"]
        == f'"{small_directory.cid}.car.entity.0:10"'
    )


@pytest.mark.parametrize("method", ["GET", "HEAD"])
@pytest.mark.parametrize(
    ("params", "code"),
    [
        ({"dag-scope": "bogus"}, "invalid_dag_scope"),
        ({"entity-bytes": "zz"}, "invalid_entity_bytes"),
    ],
)
def test_car_parameters_are_checked_before_if_none_match(
    cas_service: ServiceProcess,
    small_directory: Block,
    method: str,
    params: dict[str, str],
    code: str,
) -> None:
    """``If-None-Match: *`` matched before the scope was looked at: 304 for a bogus one."""
    response = httpx.request(
        method,
        f"{cas_service.url}/ipfs/{small_directory.cid}",
        params={"format": "car", **params},
        headers={"If-None-Match": "*"},
        timeout=30,
    )
    assert response.status_code == 400
    if method == "GET":
        assert error(response)["code"] == code
