"""A storage node behind an external node (anvil), killed (SIGKILL) while its
``Registry.advertise`` transaction is still pending: the resumed job advertises nothing more.

Real anvil, ledger (fronting anvil), cas and storage processes; the storage node reaches the
ledger through a forwarding proxy. On the first advertise transaction the proxy stops anvil's
mining, forwards it (anvil keeps it pending) and kills the node. On the next advertise
transaction it forwards it, then mines: both are mined if the resumed node signed a second.
"""

from __future__ import annotations

from pathlib import Path

import httpx

from robocloud.cid import parse_cid
from robocloud.identity import Identity
from robocloud.ingest import Ingest
from robocloud.ledger import JsonRpcClient, Ledger, LedgerService
from tests.conftest import ServiceFactory
from tests.integration.robocloud.ledger.nodes import ethereum_node
from tests.integration.services.ledger.conftest import ledger_fronting
from tests.integration.services.storage.ledger_proxy import (
    ADVERTISE,
    LedgerProxy,
    sends,
    serving,
    storage_behind,
    upload_imu_bag,
)
from tests.procs import ServiceProcess
from tests.scripted_http import Exchange, Reply


class KillWhilePending(LedgerProxy):
    """A proxy script: the first advertise transaction reaches anvil with mining stopped, and
    the storage node is killed before any answer; the next one is forwarded, then mined."""

    def __init__(self, ledger: ServiceProcess, anvil: JsonRpcClient) -> None:
        super().__init__(ledger)
        self.anvil = anvil
        self.advertises = 0

    def __call__(self, exchange: Exchange) -> Reply:
        with self.lock:
            advertise = exchange.method == "POST" and sends(exchange.body, ADVERTISE)
            self.advertises += advertise
            number = self.advertises if advertise else 0
        if number == 1:
            self.anvil.request("evm_setAutomine", [False])
        answer = self.forward(exchange)
        if number == 1:
            return self.kill_storage()
        if number == 2:
            self.anvil.request("evm_setAutomine", [True])
            self.anvil.request("evm_mine", [])
        return self.answer(answer)


def test_kill_9_while_the_advertise_is_pending_advertises_the_dataset_once(
    service_factory: ServiceFactory, identity: Identity, tmp_path: Path
) -> None:
    """The resumed job looked for a mined ``Advertised`` event only, found none, and signed a
    second advertise with the next nonce: both were mined, the dataset advertised twice."""
    with ethereum_node(tmp_path / "anvil.log") as anvil_url, JsonRpcClient(anvil_url) as anvil:
        ledger = ledger_fronting(service_factory, anvil_url, anvil, tmp_path / "ledger")
        cas = service_factory("cas")
        proxy = KillWhilePending(ledger, anvil)
        with serving(proxy) as server:
            env = {"ROBOCLOUD_STORAGE_ANCHOR": "false"}
            storage = storage_behind(proxy, server.url, service_factory, cas, env)
            node = str(httpx.get(f"{storage.url}/v1/node", timeout=10).json()["address"])
            anvil.request("hardhat_setBalance", [node, hex(10**18)])
            _, job_id = upload_imu_bag(storage, identity, tmp_path / "run.bag")
            proxy.wait_killed("the storage node to send its advertise transaction")

            storage.start()
            with Ingest(storage.url, identity) as ing:
                done = ing.wait(job_id, timeout_s=180)
            assert done["status"] == "succeeded", done["error"]

        with LedgerService(ledger.url) as service:
            addresses = service.contracts()
        with Ledger(JsonRpcClient(anvil_url), addresses) as chain:
            advertised = chain.advertisements(cid=parse_cid(done["dataset"]["cid"], "bag").binary)
    assert [(event.advertiser, event.tx_hash) for event in advertised] == [
        (node, done["dataset"]["tx"])
    ]
