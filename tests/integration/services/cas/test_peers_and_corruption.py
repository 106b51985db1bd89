"""Blocks that rot on disk are never served; missing blocks come from verified peers."""

from __future__ import annotations

from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler

import httpx
import pytest

from robocloud.car import write_car
from robocloud.cas import Cas
from robocloud.cid import CID, DAG_PB, Block
from robocloud.client import ServiceClient
from robocloud.dagpb import Link, PBNode
from robocloud.errors import ApiError, RateLimitedError
from robocloud.identity import Identity
from robocloud.unixfs import import_bytes
from tests.conftest import ServiceFactory
from tests.integration.services.cas.conftest import (
    QUIET_GC,
    corrupt_block,
    error_of,
    post_files,
    repo_stat,
    store_unchanged,
)
from tests.procs import ServiceProcess
from tests.scripted_http import serving

DATA = bytes(range(251)) * 3133  # three distinct leaves under a root


class LyingGateway(BaseHTTPRequestHandler):
    """A peer that answers every block request with the wrong bytes."""

    def do_GET(self) -> None:
        body = b"these are not the bytes you asked for"
        self.send_response(200)
        self.send_header("Content-Type", "application/vnd.ipld.raw")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: object) -> None:
        return None


@pytest.fixture
def liar() -> Iterator[str]:
    with serving(LyingGateway) as url:
        yield url


def metric(service: ServiceProcess, name: str, **labels: str) -> float:
    text = httpx.get(f"{service.url}/metrics").text
    for line in text.splitlines():
        if line.startswith(name) and all(f'{k}="{v}"' in line for k, v in labels.items()):
            return float(line.rsplit(" ", 1)[1])
    return 0.0


def peer_of(factory: ServiceFactory, *peers: str) -> ServiceProcess:
    return factory("cas", {**QUIET_GC, "ROBOCLOUD_CAS_PEERS": ",".join(peers)})


def test_corrupted_block_is_never_served(
    cas: Cas, cas_service: ServiceProcess, identity: Identity
) -> None:
    cid = cas.add_bytes(b"a single-block file")
    corrupt_block(cas_service.data_dir, cid)
    response = httpx.get(f"{cas_service.url}/ipfs/{cid}")
    assert response.status_code == 404
    error = response.json()["error"]
    assert "corrupted on disk and quarantined" in error["message"]
    assert error["details"] == {"cid": str(cid)}
    assert len(list((cas_service.data_dir / "quarantine").iterdir())) == 1
    assert metric(cas_service, "robocloud_cas_corrupt_blocks_total") == 1
    assert httpx.get(f"{cas_service.url}/ipfs/{cid}?format=raw").status_code == 404
    assert "corrupted block quarantined" in cas_service.log()


def test_corruption_deep_in_a_file_cuts_the_body_off(cas: Cas, cas_service: ServiceProcess) -> None:
    data = bytes(range(251)) * 25066  # 6 MiB: the corrupt leaf lies past the first batch
    blocks, root = import_bytes(data)
    assert cas.add_bytes(data) == root
    last_leaf = blocks[-2].cid
    corrupt_block(cas_service.data_dir, last_leaf)
    received = bytearray()

    def download() -> None:
        with httpx.stream("GET", f"{cas_service.url}/ipfs/{root}", timeout=30) as response:
            assert response.status_code == 200
            for chunk in response.iter_raw():
                received.extend(chunk)

    with pytest.raises(httpx.RemoteProtocolError):
        download()
    assert 0 < len(received) < len(data)
    assert data.startswith(bytes(received))


def test_missing_blocks_come_from_a_peer_and_are_cached(
    cas: Cas, cas_service: ServiceProcess, service_factory: ServiceFactory
) -> None:
    cid = cas.add_bytes(DATA)
    edge = peer_of(service_factory, cas_service.url)
    response = httpx.get(f"{edge.url}/ipfs/{cid}", timeout=30)
    assert response.content == DATA
    cas_service.stop()
    cached = httpx.get(f"{edge.url}/ipfs/{cid}", headers={"Cache-Control": "only-if-cached"})
    assert cached.status_code == 200
    assert cached.content == DATA
    assert metric(edge, "robocloud_cas_peer_fetches_total", outcome="ok") == 4


def test_a_lying_peer_is_skipped_for_the_next(
    cas: Cas, cas_service: ServiceProcess, service_factory: ServiceFactory, liar: str
) -> None:
    cid = cas.add_bytes(DATA)
    edge = peer_of(service_factory, liar, cas_service.url)
    with Cas(edge.url, Identity.generate()) as robot:
        assert robot.get(cid) == DATA
    assert metric(edge, "robocloud_cas_peer_fetches_total", peer=liar, outcome="bad_block") == 4
    assert metric(edge, "robocloud_cas_peer_fetches_total", outcome="ok") == 4
    assert "refused the gateway's block" in edge.log()


def test_only_liars_means_not_found(service_factory: ServiceFactory, liar: str) -> None:
    edge = peer_of(service_factory, liar)
    missing = CID.from_block(b"anything")
    response = httpx.get(f"{edge.url}/ipfs/{missing}")
    assert response.status_code == 404
    assert "no peer has it" in response.json()["error"]["message"]
    assert httpx.post(f"{edge.url}/api/v0/repo/stat").json()["NumObjects"] == 0


def test_a_corrupted_block_is_refetched_from_a_peer(
    cas_service: ServiceProcess, service_factory: ServiceFactory, identity: Identity
) -> None:
    edge = peer_of(service_factory, cas_service.url)
    with Cas(cas_service.url, identity) as origin, Cas(edge.url, identity) as near:
        cid = origin.add_bytes(DATA)
        assert near.add_bytes(DATA) == cid
        leaf = import_bytes(DATA)[0][1].cid
        corrupt_block(edge.data_dir, leaf)
        assert near.get(cid) == DATA
    assert metric(edge, "robocloud_cas_corrupt_blocks_total") == 1
    assert metric(edge, "robocloud_cas_peer_fetches_total", outcome="ok") == 1
    assert httpx.get(f"{edge.url}/ipfs/{leaf}?format=raw").content == DATA[262144:524288]


def test_peers_asking_each_other_do_not_loop(service_factory: ServiceFactory) -> None:
    first = service_factory("cas", QUIET_GC)
    second = peer_of(service_factory, first.url)
    missing = CID.from_block(b"nobody has this")
    assert httpx.get(f"{second.url}/ipfs/{missing}", timeout=10).status_code == 404


def test_uploads_ask_no_peer_for_what_they_link_to_and_pin_add_does(
    cas: Cas, cas_service: ServiceProcess, service_factory: ServiceFactory, identity: Identity
) -> None:
    """kubo's ``dag import`` is offline, and so are ``dag/import`` and ``block/put?pin=true``
    here: a CAR of one small node linking to a DAG of any size at the peers had the cas
    fetch all of it before the pin, past any bound an upload has. ``pin/add`` asks the
    peers, within the robot's share."""
    far = cas.add_bytes(DATA)
    edge = peer_of(service_factory, cas_service.url)
    data = PBNode([Link(far, "far", len(DATA))], b"").encode()
    near = Block(CID.from_block(data, DAG_PB, 1), data)
    with ServiceClient(edge.url, identity, retries=0) as signed, Cas(edge.url, identity) as robot:
        car = b"".join(write_car([near.cid], [near]))
        answer = post_files(signed, "/api/v0/dag/import", ("near.car", car)).json()
        assert answer["Root"]["Cid"] == {"/": str(near.cid)}
        assert answer["Root"]["PinErrorMsg"] == (
            f"block {far} of the DAG is missing; {near.cid} was not pinned"
        )
        assert repo_stat(edge.url)["NumObjects"] == 1
        with store_unchanged(edge), pytest.raises(ApiError) as exc:
            post_files(signed, "/api/v0/block/put?pin=true&cid-codec=dag-pb", ("block", near.data))
        assert error_of(exc, 404, "block_not_found").details == {
            "cid": str(near.cid),
            "missing": str(far),
        }
        assert metric(edge, "robocloud_cas_peer_fetches_total") == 0
        robot.pin(near.cid)
    assert metric(edge, "robocloud_cas_peer_fetches_total", outcome="ok") == 4
    assert repo_stat(edge.url)["NumObjects"] == 5


def test_reads_keep_what_they_fetch_from_peers_within_the_hours_bound(
    cas: Cas, cas_service: ServiceProcess, service_factory: ServiceFactory
) -> None:
    """Nobody signs a read, and every block a read fetched was kept until a collection past
    the grace period: one stranger reading the peers' content filled the disk. Past the
    hour's bound a fetched block is served, verified, and not kept."""
    cid = cas.add_bytes(DATA)
    blocks, _ = import_bytes(DATA)
    root, first_leaf = blocks[-1], blocks[0]
    edge = service_factory(
        "cas",
        {
            **QUIET_GC,
            "ROBOCLOUD_CAS_PEERS": cas_service.url,
            "ROBOCLOUD_CAS_MAX_CACHED_BYTES_PER_HOUR": str(len(root.data) + len(first_leaf.data)),
        },
    )
    for _ in range(2):
        assert httpx.get(f"{edge.url}/ipfs/{cid}", timeout=30).content == DATA
    assert repo_stat(edge.url)["NumObjects"] == 2
    cached = {"Cache-Control": "only-if-cached"}
    assert httpx.get(f"{edge.url}/ipfs/{first_leaf.cid}?format=raw", headers=cached).content == (
        first_leaf.data
    )
    assert (
        httpx.get(f"{edge.url}/ipfs/{blocks[1].cid}?format=raw", headers=cached).status_code == 412
    )
    assert metric(edge, "robocloud_cas_peer_fetches_total", outcome="ok") == 6
    assert metric(edge, "robocloud_cas_peer_blocks_not_kept_total") == 4


def test_pin_add_charges_what_it_fetches_to_the_robots_new_bytes(
    cas: Cas, cas_service: ServiceProcess, service_factory: ServiceFactory, identity: Identity
) -> None:
    """``pin/add`` keeps what it fetches; uncharged, a robot pinning and unpinning DAGs at
    the peers wrote without bound. Past its new bytes of the hour the walk stops."""
    cid = cas.add_bytes(DATA)
    small = cas.add_bytes(b"small enough")
    blocks, _ = import_bytes(DATA)
    fetched = len(blocks[-1].data) + len(blocks[0].data)
    edge = service_factory(
        "cas",
        {
            **QUIET_GC,
            "ROBOCLOUD_CAS_PEERS": cas_service.url,
            "ROBOCLOUD_CAS_MAX_WRITTEN_BYTES_PER_ROBOT_PER_HOUR": str(fetched + 1000),
        },
    )
    with Cas(edge.url, identity, retries=0) as robot:
        with pytest.raises(ApiError) as exc:
            robot.pin(cid)
        error = error_of(exc, 429, "write_rate_exceeded")
        assert isinstance(exc.value, RateLimitedError)
        error.details.pop("retry_after")
        assert error.details == {
            "robot": identity.address,
            "size": len(blocks[1].data),
            "written": fetched,
            "limit": fetched + 1000,
        }
        assert robot.pins() == {}
        robot.pin(small)
        assert robot.pin_share().written_bytes_last_hour == fetched + len(b"small enough")
    assert metric(edge, "robocloud_cas_peer_fetches_total", outcome="ok") == 4
