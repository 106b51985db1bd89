"""``ipfs add -r`` and ``-w`` through kubo's multipart: the CIDs kubo and js-ipfs-unixfs give."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx
import pytest

from robocloud.car import write_car
from robocloud.cas import Cas
from robocloud.cid import CID
from robocloud.client import ServiceClient
from robocloud.dagpb import Link
from robocloud.directory import sharded_directory
from robocloud.errors import ApiError
from robocloud.identity import Identity
from robocloud.unixfs import import_bytes
from tests.conftest import ServiceFactory
from tests.flood import flooding
from tests.integration.services.cas.conftest import (
    QUIET_GC,
    error_of,
    multipart,
    pin_list,
    store_unchanged,
    tree_multipart,
)
from tests.procs import SHARED_DATA, ServiceProcess

FIXTURE_DIR = SHARED_DATA / "ipfs" / "car" / "gateway-conformance" / "dag_car_input" / "dir"
HAMT_10000 = "bafybeig6pxxinjawyoovbpcplssgrpnuf3pisprbis7mccrfieojv22eny"
"""js-ipfs-unixfs's importer on 10,000 files ``file-NNNNN.txt`` holding ``file N\\n`` (CIDv1)."""


@pytest.fixture(scope="module")
def cas_service(shared_cas_service: ServiceProcess) -> ServiceProcess:
    return shared_cas_service


def add(
    signed: ServiceClient, body: bytes, content_type: str, **params: Any
) -> list[dict[str, Any]]:
    response = signed.request(
        "POST", "/api/v0/add", params=params, content=body, headers={"Content-Type": content_type}
    )
    return [json.loads(line) for line in response.text.splitlines()]


def test_a_directory_adds_to_the_fixtures_cids_in_kubos_order(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    body, content_type = tree_multipart(FIXTURE_DIR)
    lines = add(signed, body, content_type, **{"cid-version": 1})
    assert [(line["Name"], line["Hash"]) for line in lines] == [
        ("dir/a-file.txt", "bafkreidw23elffhagxz3oi6ctoibqouzfowfn3bwcvq2yzgd5n5h4gjyou"),
        ("dir/b-file.txt", "bafkreiaeqsxxqwmsnhzhrlyr2udn25hpj24bs7gzcgkhbrkmhcuikcgh4a"),
        ("dir/subdir/leaf.txt", "bafkreihdhgb5vyuqu7jssreyo3h567obewtqq37fi5hr2w4um5icacry7m"),
        ("dir/subdir", "bafybeiaq6e55xratife7s5cmzjcmwy4adzzlk74sbdpfcq72gus6cweeeq"),
        ("dir", "bafybeidlbwbu73tbjr3atntjz4lq5ego5w2uyof35vvwcnheaftzi3rndu"),
    ]
    pins = pin_list(cas_service.url)["Keys"]
    assert "bafybeidlbwbu73tbjr3atntjz4lq5ego5w2uyof35vvwcnheaftzi3rndu" in pins
    assert "bafkreidw23elffhagxz3oi6ctoibqouzfowfn3bwcvq2yzgd5n5h4gjyou" not in pins


def test_parents_a_file_path_implies_are_built_and_pinned_without_directory_parts(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """Only ``dir/...`` file parts: the same CIDs as with kubo's directory parts, and ``dir``
    pinned (before, nothing was built or pinned, and the next GC took the files)."""
    files = sorted(path for path in FIXTURE_DIR.rglob("*") if path.is_file())
    parts = [(quote(f"dir/{p.relative_to(FIXTURE_DIR)}", safe=""), p.read_bytes()) for p in files]
    lines = add(signed, *multipart(*parts), **{"cid-version": 1})
    assert [line["Name"] for line in lines][-2:] == ["dir/subdir", "dir"]
    assert lines[-1]["Hash"] == "bafybeidlbwbu73tbjr3atntjz4lq5ego5w2uyof35vvwcnheaftzi3rndu"
    assert lines[-1]["Hash"] in pin_list(cas_service.url)["Keys"]
    signed.request("POST", "/api/v0/repo/gc")
    leaf = httpx.get(f"{cas_service.url}/ipfs/{lines[-1]['Hash']}/subdir/leaf.txt")
    assert leaf.content == (FIXTURE_DIR / "subdir" / "leaf.txt").read_bytes()


def test_wrap_with_directory_matches_kubos_add_rw(signed: ServiceClient, tmp_path: Path) -> None:
    """gateway-raw-block.car was made with ``ipfs add -Qrw --cid-version 1 dir``."""
    root = tmp_path / "dir"
    root.mkdir()
    (root / "ascii.txt").write_bytes(b"hello application/vnd.ipld.raw\n")
    body, content_type = tree_multipart(root)
    lines = add(signed, body, content_type, **{"cid-version": 1, "wrap-with-directory": "true"})
    assert lines[-1] == {
        "Name": "",
        "Hash": "bafybeie72edlprgtlwwctzljf6gkn2wnlrddqjbkxo3jomh4n7omwblxly",
        "Size": lines[-1]["Size"],
    }


def test_ten_thousand_entries_shard_as_the_reference_does(
    signed: ServiceClient, tmp_path: Path
) -> None:
    root = tmp_path / "dir"
    root.mkdir()
    for i in range(10_000):
        (root / f"file-{i:05d}.txt").write_bytes(f"file {i}\n".encode())
    body, content_type = tree_multipart(root)
    lines = add(signed, body, content_type, **{"cid-version": 1})
    assert len(lines) == 10_001
    assert lines[-1]["Hash"] == HAMT_10000


def test_a_fanout_16_hamt_resolves_its_names_through_the_gateway(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """kubo with ``Import.UnixFSHAMTDirectoryMaxFanout`` 16: 4 hash bits a level, so a path
    into the shard found ``hello.txt`` listed yet answered 404 while a whole byte was used."""
    blocks, entries = [], []
    for name, text in [("hello.txt", b"hello\n")] + [(f"f{i}", f"{i}".encode()) for i in range(40)]:
        file_blocks, cid = import_bytes(text)
        blocks += file_blocks
        entries.append(Link(cid, name, sum(len(block.data) for block in file_blocks)))
    shards, root = sharded_directory(entries, 1, fanout=16)
    body, content_type = multipart(("hamt.car", b"".join(write_car([root.cid], blocks + shards))))
    signed.request(
        "POST", "/api/v0/dag/import", content=body, headers={"Content-Type": content_type}
    )
    hello = httpx.get(f"{cas_service.url}/ipfs/{root.cid}/hello.txt")
    assert (hello.status_code, hello.content) == (200, b"hello\n")
    assert httpx.get(f"{cas_service.url}/ipfs/{root.cid}/f39").content == b"39"
    assert "hello.txt" in httpx.get(f"{cas_service.url}/ipfs/{root.cid}/").text


def test_escaped_names_are_unescaped_as_kubo_does(signed: ServiceClient) -> None:
    body, content_type = multipart(("%C3%A4%20b.bin", b"x"), ("plus+sign.txt", b"y"))
    lines = add(signed, body, content_type, **{"cid-version": 1})
    assert [line["Name"] for line in lines] == ["ä b.bin", "plus sign.txt"]


@pytest.mark.parametrize(
    "name", ["../x", "dir/../../x", "/etc/passwd", "a//b", "dir/./x", "%zz"], ids=repr
)
def test_names_that_escape_the_root_store_nothing(
    signed: ServiceClient, cas_service: ServiceProcess, name: str
) -> None:
    body, content_type = multipart((name, b"escape"))
    with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
        add(signed, body, content_type, **{"wrap-with-directory": "true"})
    assert exc.value.status == 400
    assert exc.value.code in ("invalid_path", "invalid_multipart")


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("trickle", "true"),
        ("inline", "true"),
        ("nocopy", "true"),
        ("hash", "sha3-256"),
        ("mtime", "1"),
        ("to-files", "/x"),
    ],
)
def test_an_option_not_implemented_is_refused_not_ignored(
    signed: ServiceClient, cas_service: ServiceProcess, option: str, value: str
) -> None:
    body, content_type = multipart(("f", b"hello"))
    with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
        add(signed, body, content_type, **{option: value})
    assert error_of(exc, 400, "unsupported_option").details == {"field": option}


def test_the_harmless_defaults_of_kubos_clients_are_accepted(signed: ServiceClient) -> None:
    body, content_type = multipart(("f", b"defaults"))
    lines = add(
        signed,
        body,
        content_type,
        **{"trickle": "false", "hash": "sha2-256", "progress": "true", "stream-channels": "true"},
    )
    assert lines[0] == {"Name": "f", "Bytes": 8}
    assert lines[1]["Name"] == "f"


def test_too_many_entries_are_refused_whole(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    small = service_factory("cas", {**QUIET_GC, "ROBOCLOUD_CAS_MAX_UPLOAD_ENTRIES": "5"})
    root = tmp_path / "dir"
    root.mkdir()
    for i in range(5):
        (root / f"{i}.txt").write_bytes(b"x")
    body, content_type = tree_multipart(root)
    with ServiceClient(small.url, identity, retries=0) as signed, pytest.raises(ApiError) as exc:
        add(signed, body, content_type)
    assert error_of(exc, 413, "too_many_entries").details == {"field": "entries", "limit": 5}
    assert httpx.post(f"{small.url}/api/v0/repo/stat").json()["NumObjects"] == 0


FLOODERS = 40
ENTRIES = 20_000


def html_listing(client: httpx.Client, url: str, root: CID) -> httpx.Response:
    return client.get(f"{url}/ipfs/{root}/", headers={"Accept": "text/html"})


def kubo_ls(client: httpx.Client, url: str, root: CID) -> httpx.Response:
    return client.post(f"{url}/api/v0/ls", params={"arg": str(root)})


def listed_entries(answer: httpx.Response) -> int:
    if answer.headers["content-type"].startswith("text/html"):
        return answer.text.count("<tr><td>")
    return len(answer.json()["Objects"][0]["Links"])


@pytest.mark.parametrize("ask", [html_listing, kubo_ls], ids=["gateway-html", "kubo-ls"])
def test_a_flood_of_big_listings_starves_no_other_read(
    cas: Cas,
    cas_service: ServiceProcess,
    tmp_path: Path,
    ask: Callable[[httpx.Client, str, CID], httpx.Response],
) -> None:
    """A listing of 20,000 entries is 0.4-0.7 s of CPU and megabytes of HTML or JSON, free
    for anyone. The HTML was rendered on the event loop and ``ls`` ran unbounded on worker
    threads: 40 clients asking again and again held a five-byte file's read for 12 s (the
    HTML) or past 60 s (``ls``). Listings now take turns on worker threads, two at a time,
    and one client (the flood's address) has one of them: another client's listing is
    answered in full while the flood goes on."""
    source = tmp_path / "many"
    source.mkdir()
    for index in range(ENTRIES):
        (source / f"file-{index:06d}.txt").write_bytes(str(index).encode())
    root = cas.add_directory(source)
    small = cas.add_bytes(b"hello")
    with flooding(lambda client: ask(client, cas_service.url, root), FLOODERS) as flood:
        time.sleep(2)
        # The honest listing has the turn the flood's address cannot take; its 20,000 entries
        # took past 5 s beside a pytest-xdist worker, so the client waits longer than that.
        with httpx.Client(timeout=30) as honest:
            read = honest.get(f"{cas_service.url}/ipfs/{small}")
            ready = honest.get(f"{cas_service.url}/readyz")
            listing = ask(honest, cas_service.url, root)
        still_flooding = flood.running()
    assert read.content == b"hello"
    assert ready.json()["status"] == "ready"
    assert listed_entries(listing) == ENTRIES
    assert still_flooding
    refused = [answer for answer in flood.answers if answer.status_code != 200]
    assert refused
    for answer in flood.answers:
        if answer.status_code == 200:
            assert listed_entries(answer) == ENTRIES
    assert 429 in {answer.status_code for answer in refused}
    for answer in refused:
        error = answer.json()["error"]
        if answer.status_code == 503:  # its turn of the share came, a slot did not in time
            assert (error["code"], error["details"]) == ("busy", {"slots": 2, "wait_s": 5.0})
        else:
            assert answer.status_code == 429
            assert error["code"] == "rate_limited"
            assert error["details"] == {"share": 1, "slots": 2, "wait_s": 5.0}
