"""A new storage node's anchorer and dataset publisher both register the node before their
first transaction: the node registers once, and neither fails for the other's registration.

Real ledger, cas and storage processes; the storage node reaches the ledger through a
forwarding proxy that holds the node's first ``register`` transaction until the node reads
its standing again (or 10 s passed): where two writers that do not wait on one another both
find the node unregistered.
"""

from __future__ import annotations

import threading
from pathlib import Path

from robocloud.identity import Identity
from robocloud.ingest import Ingest
from tests.conftest import ServiceFactory
from tests.integration.services.storage.ledger_proxy import (
    LedgerProxy,
    rpc_calls,
    selector,
    sends,
    serving,
    storage_behind,
    upload_imu_bag,
)
from tests.procs import ServiceProcess
from tests.scripted_http import Exchange, Reply

REGISTER = selector("Registry", "register")
STANDING = selector("Registry", "isActiveWithRole")
"""The selector of the first view call reading a node's standing."""


def _reads_standing(body: bytes) -> bool:
    return any(
        isinstance(call, dict)
        and call.get("method") == "eth_call"
        and str(call["params"][0]["data"]).startswith("0x" + STANDING.hex())
        for call in rpc_calls(body)
    )


class HoldFirstRegister(LedgerProxy):
    """A proxy script: every request goes to the ledger, the first register transaction once
    the node read its standing again, or 10 s passed."""

    def __init__(self, ledger: ServiceProcess) -> None:
        super().__init__(ledger)
        self.holding = threading.Event()
        self.read_again = threading.Event()

    def __call__(self, exchange: Exchange) -> Reply:
        with self.lock:
            hold = not self.holding.is_set() and sends(exchange.body, REGISTER)
            if hold:
                self.holding.set()
            elif self.holding.is_set() and _reads_standing(exchange.body):
                self.read_again.set()
        if hold:
            self.read_again.wait(10)
        return self.answer(self.forward(exchange))


def test_the_anchorer_and_the_first_publish_register_the_node_once(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """Each read the node unregistered and registered it: one registration reverted
    ("Registry: already registered"), failing the first dataset's publish or an anchor."""
    ledger = service_factory("ledger")
    cas = service_factory("cas")
    proxy = HoldFirstRegister(ledger)
    with serving(proxy) as server:
        env = {"ROBOCLOUD_STORAGE_EPOCH_S": "0.2"}
        storage = storage_behind(proxy, server.url, service_factory, cas, env)
        _, job_id = upload_imu_bag(storage, identity, tmp_path / "run.bag")
        with Ingest(storage.url, identity) as ingest:
            done = ingest.wait(job_id, timeout_s=120)
    assert done["status"] == "succeeded", done["error"]
    assert "error" not in done["dataset"], done["dataset"]
    assert proxy.holding.is_set()
    assert "already registered" not in storage.log()
