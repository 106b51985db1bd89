"""A storage node behind an external node (anvil) whose anchor transaction stays pending, as
one whose gas price fell behind a public chain's base fee does: the next attempt resends it,
waits one receipt timeout more, then replaces it with the same anchor at a higher price, and
the epoch is anchored once, by the replacement.

Real anvil, ledger (fronting anvil), cas and storage processes; the storage node reaches the
ledger through a forwarding proxy, which stops anvil's mining on the first anchor transaction
and mines again once an anchor transaction of another hash arrives.
"""

from __future__ import annotations

from pathlib import Path

import httpx

from robocloud.identity import Identity
from robocloud.ledger import JsonRpcClient, Ledger, LedgerService
from robocloud.ledger.transactions import transaction_hash
from tests.conftest import ServiceFactory
from tests.integration.robocloud.ledger.nodes import ethereum_node
from tests.integration.services.ledger.conftest import ledger_fronting
from tests.integration.services.storage.counter import write_counter_records
from tests.integration.services.storage.ledger_proxy import (
    LedgerProxy,
    rpc_calls,
    selector,
    sends,
    storage_behind,
)
from tests.integration.services.storage.test_anchor_pending import transactions_of, wait_anchored
from tests.integration.services.storage.test_anchoring import node_state
from tests.procs import ServiceProcess, free_port
from tests.scripted_http import Exchange, Reply, scripted_server

ANCHOR = selector("AnchorLog", "anchor")


class StuckUntilRepriced(LedgerProxy):
    """Mining stops on the first anchor transaction and resumes on the first anchor
    transaction of another hash (its replacement): every anchor transaction seen is kept,
    with its gas price as the node held it (a replaced one is gone from the node after)."""

    def __init__(self, ledger: ServiceProcess, anvil: JsonRpcClient) -> None:
        super().__init__(ledger)
        self.anvil = anvil
        self.anchor_txs: list[str] = []
        self.prices: dict[str, int] = {}

    def __call__(self, exchange: Exchange) -> Reply:
        anchor = exchange.method == "POST" and sends(exchange.body, ANCHOR)
        with self.lock:
            if anchor and not self.anchor_txs:
                self.anvil.request("evm_setAutomine", [False])
        answer = self.forward(exchange)
        if anchor:
            tx = sent_hash(exchange.body)
            with self.lock:
                if tx not in self.anchor_txs:
                    self.anchor_txs.append(tx)
                    self.prices[tx] = gas_price(self.anvil, tx)
                if len(self.anchor_txs) == 2:
                    self.anvil.request("evm_setAutomine", [True])
                    self.anvil.request("evm_mine", [])
        return self.answer(answer)


def sent_hash(body: bytes) -> str:
    """The hash of the transaction a request sends (a resend is refused "already known",
    so the answer does not always carry it)."""
    (call,) = [c for c in rpc_calls(body) if c.get("method") == "eth_sendRawTransaction"]
    return transaction_hash(bytes.fromhex(str(call["params"][0]).removeprefix("0x")))


def gas_price(anvil: JsonRpcClient, tx: str) -> int:
    return int(anvil.request("eth_getTransactionByHash", [tx])["gasPrice"], 16)


def test_an_anchor_pending_past_the_receipt_timeout_is_replaced_at_a_higher_price(
    service_factory: ServiceFactory, tmp_path: Path
) -> None:
    with ethereum_node(tmp_path / "anvil.log") as anvil_url, JsonRpcClient(anvil_url) as anvil:
        storage_port = free_port()
        storage_url = f"http://127.0.0.1:{storage_port}"
        ledger = ledger_fronting(
            service_factory, anvil_url, anvil, tmp_path / "ledger", storage_url
        )
        cas = service_factory("cas")
        proxy = StuckUntilRepriced(ledger, anvil)
        with scripted_server(proxy, answer_audience=False) as server:
            env = {
                "ROBOCLOUD_STORAGE_EPOCH_S": "0.2",
                "ROBOCLOUD_STORAGE_ANCHOR_RETRY_S": "0.2",
                "ROBOCLOUD_STORAGE_RECEIPT_TIMEOUT_S": "2",
            }
            storage = storage_behind(
                proxy, server.url, service_factory, cas, env, port=storage_port
            )
            node = str(node_state(storage)["address"])
            anvil.request("hardhat_setBalance", [node, hex(10**18)])
            write_counter_records(storage, Identity.generate(), 0, 40)
            wait_anchored(storage, 1, "the stuck epoch anchored by its replacement")
            recorded = httpx.get(f"{storage.url}/v1/epochs/1", timeout=10).json()["anchor"]
            original, replacement = proxy.anchor_txs[:2]

        with LedgerService(ledger.url) as service:
            addresses = service.contracts()
        with Ledger(JsonRpcClient(anvil_url), addresses) as chain:
            anchored = chain.anchors(node=node, epoch=1)
        mined = [tx["hash"].lower() for tx in transactions_of(anvil, node)]
    assert [str(anchor.tx_hash).lower() for anchor in anchored] == [replacement]
    assert recorded["tx"].lower() == replacement
    assert original not in mined
    assert proxy.prices[replacement] >= proxy.prices[original] * 9 // 8
