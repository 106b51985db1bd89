"""Garbage collection keeps every pinned block; content and pins survive a restart."""

from __future__ import annotations

import json
import time

import httpx

from robocloud.cas import Cas
from robocloud.cid import CID
from robocloud.client import ServiceClient
from robocloud.identity import Identity
from tests.conftest import ServiceFactory
from tests.integration.services.cas.conftest import QUIET_GC, multipart, repo_stat

PINNED = bytes(range(251)) * 2100  # three distinct leaves and a root
LOOSE = b"\x01" * 400_000


def gc(client: ServiceClient) -> set[str]:
    response = client.request("POST", "/api/v0/repo/gc")
    return {json.loads(line)["Key"]["/"] for line in response.text.splitlines()}


def test_gc_removes_unpinned_blocks_and_never_pinned_ones(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    service = service_factory("cas", {**QUIET_GC, "ROBOCLOUD_CAS_GC_GRACE_S": "0"})
    with Cas(service.url, identity) as cas, ServiceClient(service.url, identity) as client:
        kept = cas.add_bytes(PINNED)
        loose = cas.add_bytes(LOOSE, pin=False)
        body, content_type = multipart(("b", b"a lone block"))
        client.request(
            "POST", "/api/v0/block/put", content=body, headers={"Content-Type": content_type}
        )
        before = repo_stat(service.url)
        assert before["NumObjects"] == 4 + 3 + 1
        removed = gc(client)
        assert len(removed) == 3 + 1
        assert str(CID.from_block(b"a lone block")) in removed
        assert repo_stat(service.url)["NumObjects"] == 4
        assert repo_stat(service.url)["RepoSize"] < before["RepoSize"]
        assert cas.get(kept) == PINNED
        assert httpx.get(f"{service.url}/ipfs/{loose}").status_code == 404
        assert gc(client) == set()


def test_gc_spares_blocks_within_the_grace_period(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    service = service_factory("cas", {**QUIET_GC, "ROBOCLOUD_CAS_GC_GRACE_S": "3600"})
    with Cas(service.url, identity) as cas, ServiceClient(service.url, identity) as client:
        loose = cas.add_bytes(LOOSE, pin=False)
        assert gc(client) == set()
        assert cas.get(loose) == LOOSE


def test_periodic_gc_runs_by_itself(service_factory: ServiceFactory, identity: Identity) -> None:
    service = service_factory(
        "cas", {"ROBOCLOUD_CAS_GC_GRACE_S": "0", "ROBOCLOUD_CAS_GC_INTERVAL_S": "0.5"}
    )
    with Cas(service.url, identity) as cas:
        cas.add_bytes(LOOSE, pin=False)
        kept = cas.add_bytes(b"pinned")
        deadline = time.monotonic() + 10
        while repo_stat(service.url)["NumObjects"] > 1 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert repo_stat(service.url)["NumObjects"] == 1
        assert cas.get(kept) == b"pinned"


def test_content_and_pins_survive_restart(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    service = service_factory("cas", QUIET_GC)
    with Cas(service.url, identity) as cas:
        cid = cas.add_bytes(PINNED)
    service.restart()
    with Cas(service.url, identity) as cas:
        assert cas.get(cid) == PINNED
        assert cas.pins()[str(cid)]["Owners"] == [identity.address]
    service.stop(kill=True)
    service.start()
    with Cas(service.url, identity) as cas:
        assert cas.get(cid) == PINNED
