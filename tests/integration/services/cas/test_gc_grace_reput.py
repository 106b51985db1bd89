"""A block pushed again gets the grace period again, however long ago it was first stored.

Robot A stores content unpinned; long after, robot B pushes the same content and then pins
the root linking it, as docs/cas.md tells robots to. A collection in between took B's
blocks, since their packs were committed long ago, and B's pin failed 404 block_not_found.
The packs are made old by dating their indexes back while the service is stopped: the
grace period stays an hour, far longer than the test.
"""

from __future__ import annotations

import json
import os
import time
from typing import Any

from robocloud.car import write_car
from robocloud.cas import Cas
from robocloud.cid import CID, DAG_PB, Block
from robocloud.client import ServiceClient
from robocloud.dagpb import Link, PBNode
from robocloud.identity import Identity
from tests.conftest import ServiceFactory
from tests.integration.services.cas.conftest import QUIET_GC, multipart
from tests.procs import ServiceProcess

HOUR = 3600
LEAF = b"a leaf two robots push " * 10
LEAF_CID = CID.from_block(LEAF)
FILE = b"a file two robots add " * 1000
CAR_LEAF = b"a leaf two robots import in a CAR"
CAR_NODE = PBNode([Link(CID.from_block(CAR_LEAF), "leaf", len(CAR_LEAF))], None).encode()
CAR_ROOT = CID.from_block(CAR_NODE, DAG_PB)
CAR = b"".join(
    write_car([CAR_ROOT], [Block(CAR_ROOT, CAR_NODE), Block(CID.from_block(CAR_LEAF), CAR_LEAF)])
)
LONELY = b"a block only robot A ever pushed"


def send(client: ServiceClient, path: str, *parts: bytes, **params: str) -> list[dict[str, Any]]:
    """A signed request, with ``parts`` as its multipart body if any; its answer's lines."""
    options: dict[str, Any] = {}
    if parts:
        body, content_type = multipart(*(("part", part) for part in parts))
        options = {"content": body, "headers": {"Content-Type": content_type}}
    response = client.request("POST", path, params=params, **options)
    return [json.loads(line) for line in response.text.splitlines()]


def push(client: ServiceClient, cas: Cas) -> CID:
    """Put the leaf, add the file and import the CAR, none pinned; the file's root."""
    send(client, "/api/v0/block/put", LEAF, **{"cid-codec": "raw"})
    send(client, "/api/v0/dag/import", CAR, **{"pin-roots": "false"})
    return cas.add_bytes(FILE, pin=False)


def date_packs_back(service: ServiceProcess, seconds: float) -> None:
    """Make every stored pack look committed ``seconds`` ago, as the next start reads it."""
    service.stop()
    then = time.time() - seconds
    for index in (service.data_dir / "packs").glob("*.idx"):
        os.utime(index, (then, then))
    service.start()


def test_content_pushed_again_is_kept_for_the_grace_period_until_it_is_pinned(
    service_factory: ServiceFactory,
) -> None:
    service = service_factory("cas", {**QUIET_GC, "ROBOCLOUD_CAS_GC_GRACE_S": str(HOUR)})
    robot_a, robot_b = Identity.generate(), Identity.generate()
    with ServiceClient(service.url, robot_a) as client, Cas(service.url, robot_a) as cas:
        file_root = push(client, cas)
        send(client, "/api/v0/block/put", LONELY, **{"cid-codec": "raw"})
    date_packs_back(service, 2 * HOUR)
    with ServiceClient(service.url, robot_b) as client, Cas(service.url, robot_b) as cas:
        assert push(client, cas) == file_root
        root = PBNode([Link(LEAF_CID, "leaf", len(LEAF))], None).encode()
        (put,) = send(client, "/api/v0/block/put", root, **{"cid-codec": "dag-pb"})
        removed = send(client, "/api/v0/repo/gc")
        assert [line["Key"] for line in removed] == [{"/": str(CID.from_block(LONELY))}]
        for pinned in (put["Key"], file_root, CAR_ROOT):
            cas.pin(pinned)
        assert cas.get(file_root) == FILE
        assert cas.block(LEAF_CID) == LEAF
