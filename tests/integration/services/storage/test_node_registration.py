"""A new storage node's anchorer and dataset publisher both register the node before their
first transaction: the node registers once, and neither fails for the other's registration.

Real ledger, cas and storage processes; the storage node reaches the ledger through a
forwarding proxy that holds the node's first ``register`` transaction until the node reads
its standing again (or 10 s passed): where two writers that do not wait on one another both
find the node unregistered.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import httpx
from eth_utils.crypto import keccak

from robocloud.identity import Identity
from robocloud.ingest import Ingest
from robocloud.ledger.abi import ContractAbi, signature
from tests.bagfactory import write_bag
from tests.conftest import ServiceFactory
from tests.integration.services.storage.test_ingest_http import START_NS, Storage, approve
from tests.integration.services.storage.test_publish_after_kill import HOP_BY_HOP, _calldata
from tests.procs import ServiceProcess
from tests.scripted_http import Exchange, Reply, scripted_server

REGISTRY = ContractAbi.load("Registry").functions
REGISTER = keccak(text=signature(REGISTRY["register"]))[:4]
STANDING = keccak(text=signature(REGISTRY["isActiveWithRole"]))[:4]
"""The selector of the first view call reading a node's standing."""


def _calls(body: bytes) -> list[Any]:
    try:
        message = json.loads(body)
    except ValueError:
        return []
    return [call for call in (message if isinstance(message, list) else [message])]


def _sends_register(body: bytes) -> bool:
    return any(
        call.get("method") == "eth_sendRawTransaction"
        and _calldata(bytes.fromhex(str(call["params"][0]).removeprefix("0x")))[:4] == REGISTER
        for call in _calls(body)
    )


def _reads_standing(body: bytes) -> bool:
    return any(
        call.get("method") == "eth_call"
        and str(call["params"][0]["data"]).startswith("0x" + STANDING.hex())
        for call in _calls(body)
    )


class HoldFirstRegister:
    """A proxy script: every request goes to the ledger, the first register transaction once
    the node read its standing again, or 10 s passed."""

    def __init__(self, ledger: ServiceProcess) -> None:
        self.upstream = httpx.Client(base_url=ledger.url, timeout=60)
        self.holding = threading.Event()
        self.read_again = threading.Event()
        self._lock = threading.Lock()

    def __call__(self, exchange: Exchange) -> Reply:
        with self._lock:
            hold = not self.holding.is_set() and _sends_register(exchange.body)
            if hold:
                self.holding.set()
            elif self.holding.is_set() and _reads_standing(exchange.body):
                self.read_again.set()
        if hold:
            self.read_again.wait(10)
        headers = {k: v for k, v in exchange.headers.items() if k not in HOP_BY_HOP}
        answer = self.upstream.request(
            exchange.method, exchange.path, headers=headers, content=exchange.body
        )
        dropped = HOP_BY_HOP | {"content-encoding"}
        kept = {k: v for k, v in answer.headers.items() if k.lower() not in dropped}
        return answer.status_code, kept, answer.content


def test_the_anchorer_and_the_first_publish_register_the_node_once(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """Each read the node unregistered and registered it: one registration reverted
    ("Registry: already registered"), failing the first dataset's publish or an anchor."""
    ledger = service_factory("ledger")
    cas = service_factory("cas")
    proxy = HoldFirstRegister(ledger)
    with scripted_server(proxy, answer_audience=False) as server:
        storage = service_factory(
            "storage",
            {
                "ROBOCLOUD_LEDGER_URL": server.url,
                "ROBOCLOUD_CAS_URL": cas.url,
                "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
                "ROBOCLOUD_STORAGE_EPOCH_S": "0.2",
            },
        )
        bag = write_bag(tmp_path / "run.bag", "ros1", 50, start_ns=START_NS)
        with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ing:
            imu = approve(client, "sensor_msgs/msg/Imu")
            ing.bind(imu, msgtype="sensor_msgs/msg/Imu")
            done = ing.wait(ing.upload(bag)["id"], timeout_s=120)
    assert done["status"] == "succeeded", done["error"]
    assert "error" not in done["dataset"], done["dataset"]
    assert proxy.holding.is_set()
    assert "already registered" not in storage.log()
