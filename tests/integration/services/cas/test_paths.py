"""Content paths on the gateway and the RPC: files, listings, index pages, CARs of a path."""

from __future__ import annotations

import http.client
import io
import json
from typing import Any

import httpx
import pytest

from robocloud.car import CarReader
from robocloud.cid import CID, IDENTITY, RAW
from robocloud.client import ServiceClient
from robocloud.identity import Identity
from tests.integration.services.cas.conftest import multipart, tree_multipart
from tests.procs import SHARED_DATA, ServiceProcess

HAMT_CAR = SHARED_DATA / "ipfs/car/gateway-conformance/single-layer-hamt-with-multi-block-files.car"
BIG = bytes(i % 251 for i in range(4 * 262_144))  # four distinct 256 KiB leaves
FILES = {
    "a.txt": b"alpha\n",
    "with space.txt": b"spaced\n",
    "ünïcödé.txt": b"unicode\n",
    "100%.txt": b"percent\n",
    "<em>&amp;.txt": b"markup\n",
    "big.bin": BIG,
    "one/two/three/four/five/deep.txt": b"five deep\n",
    "site/index.html": b"<h1>hello</h1>",
    "site/style.css": b"h1{}",
}


@pytest.fixture(scope="module")
def cas_service(shared_cas_service: ServiceProcess) -> ServiceProcess:
    return shared_cas_service


@pytest.fixture(scope="module")
def tree(cas_service: ServiceProcess, tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """The tree added as ``ipfs add -r --cid-version=1``: every path's CID, root at ``""``."""
    root = tmp_path_factory.mktemp("tree") / "tree"
    for path, data in FILES.items():
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_bytes(data)
    (root / "empty").mkdir()
    body, content_type = tree_multipart(root)
    with ServiceClient(cas_service.url, Identity.generate(), retries=0) as signed:
        response = signed.request(
            "POST",
            "/api/v0/add",
            params={"cid-version": 1},
            content=body,
            headers={"Content-Type": content_type},
        )
    lines = [json.loads(line) for line in response.text.splitlines()]
    return {line["Name"].removeprefix("tree").lstrip("/"): line["Hash"] for line in lines}


def get(service: ServiceProcess, path: str, **kwargs: Any) -> httpx.Response:
    return httpx.get(f"{service.url}{path}", timeout=30, **kwargs)


def error(response: httpx.Response) -> dict[str, Any]:
    found: dict[str, Any] = response.json()["error"]
    return found


@pytest.mark.parametrize(
    ("url_path", "name"),
    [
        ("a.txt", "a.txt"),
        ("with%20space.txt", "with space.txt"),
        ("%C3%BCn%C3%AFc%C3%B6d%C3%A9.txt", "ünïcödé.txt"),
        ("100%25.txt", "100%.txt"),
        ("one/two/three/four/five/deep.txt", "one/two/three/four/five/deep.txt"),
    ],
)
def test_files_by_path(
    cas_service: ServiceProcess, tree: dict[str, str], url_path: str, name: str
) -> None:
    response = get(cas_service, f"/ipfs/{tree['']}/{url_path}")
    assert response.status_code == 200
    assert response.content == FILES[name]
    assert response.headers["x-ipfs-roots"] == tree[name]
    head = httpx.head(f"{cas_service.url}/ipfs/{tree['']}/{url_path}")
    assert head.headers["content-length"] == str(len(FILES[name]))


def test_a_range_of_a_file_by_path(cas_service: ServiceProcess, tree: dict[str, str]) -> None:
    response = get(cas_service, f"/ipfs/{tree['']}/big.bin", headers={"Range": "bytes=10-19"})
    assert (response.status_code, response.content) == (206, BIG[10:20])


def test_a_missing_segment_is_404_naming_it(
    cas_service: ServiceProcess, tree: dict[str, str]
) -> None:
    response = get(cas_service, f"/ipfs/{tree['']}/one/two/nothing/deep.txt")
    assert response.status_code == 404
    assert error(response)["code"] == "path_not_found"
    assert error(response)["details"] == {"segment": "nothing", "cid": tree["one/two"]}


def test_a_path_through_a_file_is_400(cas_service: ServiceProcess, tree: dict[str, str]) -> None:
    response = get(cas_service, f"/ipfs/{tree['']}/a.txt/more")
    assert response.status_code == 400
    assert error(response)["code"] == "not_a_directory"
    assert error(response)["details"]["segment"] == "more"


@pytest.mark.parametrize("bad", ["one/../a.txt", "one//two", "./a.txt", "%2E%2E/a.txt", "%FF"])
def test_dot_dot_and_empty_segments_are_refused(
    cas_service: ServiceProcess, tree: dict[str, str], bad: str
) -> None:
    """Sent as written (http.client does not normalise dot segments as httpx would)."""
    connection = http.client.HTTPConnection("127.0.0.1", cas_service.port, timeout=30)
    try:
        connection.request("GET", f"/ipfs/{tree['']}/{bad}")
        response = connection.getresponse()
        status, body = response.status, json.loads(response.read())
    finally:
        connection.close()
    assert status == 400
    assert body["error"]["code"] == "invalid_path"


def test_a_directory_lists_its_entries_escaped(
    cas_service: ServiceProcess, tree: dict[str, str]
) -> None:
    response = get(cas_service, f"/ipfs/{tree['']}/", headers={"Accept": "text/html"})
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/html")
    page = response.text
    assert "&lt;em&gt;&amp;amp;.txt" in page
    assert "<em>" not in page
    assert f'href="/ipfs/{tree[""]}/with%20space.txt"' in page
    assert tree["a.txt"] in page


def test_a_directory_with_index_html_serves_it(
    cas_service: ServiceProcess, tree: dict[str, str]
) -> None:
    redirect = get(cas_service, f"/ipfs/{tree['']}/site", follow_redirects=False)
    assert redirect.status_code == 301
    assert redirect.headers["location"] == f"/ipfs/{tree['']}/site/"
    page = get(cas_service, f"/ipfs/{tree['']}/site/")
    assert page.content == FILES["site/index.html"]
    assert page.headers["content-type"] == "text/html; charset=utf-8"
    assert page.headers["content-security-policy"] == "sandbox"


def test_dag_json_gives_the_node_to_programs(
    cas_service: ServiceProcess, tree: dict[str, str]
) -> None:
    response = get(cas_service, f"/ipfs/{tree['one']}", params={"format": "dag-json"})
    assert response.headers["content-type"] == "application/vnd.ipld.dag-json"
    document = response.json()
    assert document["Data"] == {"/": {"bytes": "CAE"}}  # UnixFS Data {Type: Directory}
    assert [(link["Hash"], link["Name"]) for link in document["Links"]] == [
        ({"/": tree["one/two"]}, "two")
    ]
    by_accept = get(
        cas_service, f"/ipfs/{tree['one']}", headers={"Accept": "application/vnd.ipld.dag-json"}
    )
    assert by_accept.content == response.content


def car_cids(response: httpx.Response) -> list[str]:
    reader = CarReader(io.BytesIO(response.content))
    return [str(block.cid) for block in reader]


def test_a_car_of_a_path_holds_the_blocks_verifying_each_segment(
    cas_service: ServiceProcess, tree: dict[str, str]
) -> None:
    path = "one/two/three/four/five/deep.txt"
    response = get(cas_service, f"/ipfs/{tree['']}/{path}", params={"format": "car"})
    parents = ["/".join(path.split("/")[:depth]) for depth in range(6)]
    assert car_cids(response) == [tree[parent] for parent in parents] + [tree[path]]
    block = get(
        cas_service, f"/ipfs/{tree['']}/big.bin", params={"format": "car", "dag-scope": "block"}
    )
    assert car_cids(block) == [tree[""], tree["big.bin"]]


def test_entity_bytes_sends_only_the_blocks_covering_the_range(
    cas_service: ServiceProcess, tree: dict[str, str]
) -> None:
    url = f"/ipfs/{tree['']}/big.bin"
    chunk = 262_144
    covering = get(
        cas_service, url, params={"format": "car", "entity-bytes": f"{chunk + 10}:{2 * chunk}"}
    )
    assert len(car_cids(covering)) == 1 + 1 + 2  # the directory, the file root, two leaves
    whole = get(cas_service, url, params={"format": "car", "entity-bytes": "0:*"})
    assert len(car_cids(whole)) == 1 + 1 + 4
    outside = get(cas_service, url, params={"format": "car", "entity-bytes": f"{len(BIG)}:*"})
    assert outside.status_code == 400
    assert error(outside)["code"] == "invalid_entity_bytes"
    on_directory = get(
        cas_service, f"/ipfs/{tree['one']}", params={"format": "car", "entity-bytes": "0:10"}
    )
    assert car_cids(on_directory) == [tree["one"]]


def test_a_hamt_directory_resolves_lists_and_exports_every_shard(
    cas_service: ServiceProcess, signed: ServiceClient
) -> None:
    body, content_type = multipart(("hamt.car", HAMT_CAR.read_bytes()))
    signed.request(
        "POST", "/api/v0/dag/import", content=body, headers={"Content-Type": content_type}
    )
    root = "bafybeidbclfqleg2uojchspzd4bob56dqetqjsj27gy2cq3klkkgxtpn4i"
    entity = get(cas_service, f"/ipfs/{root}", params={"format": "car", "dag-scope": "entity"})
    assert len(car_cids(entity)) == 237
    file = get(cas_service, f"/ipfs/{root}/470.txt")
    assert file.status_code == 200
    path_car = car_cids(get(cas_service, f"/ipfs/{root}/470.txt", params={"format": "car"}))
    assert path_car[0] == root
    assert len(path_car) >= 3  # the root, the shard holding 470.txt, the file's blocks
    listing = httpx.post(f"{cas_service.url}/api/v0/ls", params={"arg": root}).json()
    links = listing["Objects"][0]["Links"]
    assert len(links) == 1000
    assert {link["Type"] for link in links} == {2}


def test_rpc_cat_and_ls_take_paths(cas_service: ServiceProcess, tree: dict[str, str]) -> None:
    cat = httpx.post(
        f"{cas_service.url}/api/v0/cat", params={"arg": f"/ipfs/{tree['']}/with space.txt"}
    )
    assert cat.content == FILES["with space.txt"]
    listing = httpx.post(f"{cas_service.url}/api/v0/ls", params={"arg": f"{tree['']}/site"})
    assert listing.json() == {
        "Objects": [
            {
                "Hash": f"{tree['']}/site",
                "Links": [
                    {
                        "Name": name,
                        "Hash": tree[f"site/{name}"],
                        "Size": size,
                        "Type": 2,
                        "Target": "",
                    }
                    for name, size in (("index.html", 14), ("style.css", 4))
                ],
            }
        ]
    }


def test_identity_cids_are_served_from_the_cid(cas_service: ServiceProcess) -> None:
    inline = CID(1, RAW, bytes([IDENTITY, 5]) + b"hello")
    raw = get(cas_service, f"/ipfs/{inline}", params={"format": "raw"})
    assert raw.content == b"hello"
    assert get(cas_service, f"/ipfs/{inline}").content == b"hello"
