"""The storage node anchors through a ledger fronting anvil, and proofs verify against anvil.

anvil has no faucet: the node's key is funded with anvil's cheat method, as an operator would
send it ether. The ledger deployed the contracts with its own admin key, so it grants the
storage-node role itself; verification then reads the anchor straight from anvil.
"""

from __future__ import annotations

from pathlib import Path

import httpx

from robocloud.identity import Identity
from robocloud.ledger import JsonRpcClient, LedgerService
from robocloud.proofs import verify_record_proof
from tests.conftest import ServiceFactory
from tests.integration.robocloud.ledger.nodes import ethereum_node
from tests.integration.services.ledger.conftest import ledger_fronting
from tests.integration.services.storage.counter import write_counter_records
from tests.integration.services.storage.test_anchoring import node_state
from tests.procs import free_port
from tests.waiting import wait_for


def test_proofs_verify_against_anvil(service_factory: ServiceFactory, tmp_path: Path) -> None:
    with ethereum_node(tmp_path / "anvil.log") as anvil, JsonRpcClient(anvil) as chain:
        storage_port = free_port()
        storage_url = f"http://127.0.0.1:{storage_port}"
        ledger = ledger_fronting(service_factory, anvil, chain, tmp_path / "ledger", storage_url)
        cas = service_factory("cas")
        storage = service_factory(
            "storage",
            {
                "ROBOCLOUD_LEDGER_URL": ledger.url,
                "ROBOCLOUD_CAS_URL": cas.url,
                "ROBOCLOUD_STORAGE_EPOCH_S": "0.2",
                "ROBOCLOUD_STORAGE_ANCHOR_RETRY_S": "0.2",
            },
            port=storage_port,
        )
        node = node_state(storage)["address"]
        chain.request("hardhat_setBalance", [node, hex(10**18)])
        write_counter_records(storage, Identity.generate(), 0, 40)
        wait_for(lambda: node_state(storage)["last_anchored_epoch"] == 1, "epoch 1 anchored")

        body = httpx.get(f"{storage.url}/v1/records/imu-1-17/proof", timeout=10).json()
        with LedgerService(ledger.url) as service:
            anchor_log = service.contracts().anchor_log
        chain_id = int(chain.request("eth_chainId", []), 16)
        proof = verify_record_proof(
            body,
            chain.request,
            anchor_log=anchor_log,
            record_id="imu-1-17",
            chain_id=chain_id,
            node=node,
        )
        assert proof.anchor.contract == anchor_log
        receipt = chain.request("eth_getTransactionReceipt", [proof.anchor.tx])
        assert int(receipt["blockNumber"], 16) == proof.anchor.block
        assert receipt["from"].lower() == node.lower()
