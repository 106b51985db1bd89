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
from tests.integration.services.storage.counter import write_counter_records
from tests.integration.services.storage.ledger_proxy import (
    LedgerProxy,
    anchoring_on_anvil,
    rpc_calls,
    selector,
    sends,
)
from tests.integration.services.storage.test_anchor_pending import transactions_of, wait_anchored
from tests.procs import ServiceProcess
from tests.scripted_http import Exchange, Reply

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
    env = {"ROBOCLOUD_STORAGE_RECEIPT_TIMEOUT_S": "2"}
    with anchoring_on_anvil(StuckUntilRepriced, service_factory, tmp_path, env) as (proxy, on):
        write_counter_records(on.storage, Identity.generate(), 0, 40)
        wait_anchored(on.storage, 1, "the stuck epoch anchored by its replacement")
        recorded = httpx.get(f"{on.storage.url}/v1/epochs/1", timeout=10).json()["anchor"]
        original, replacement = proxy.anchor_txs[:2]
        with LedgerService(on.ledger.url) as service:
            addresses = service.contracts()
        with Ledger(JsonRpcClient(on.anvil_url), addresses) as chain:
            anchored = chain.anchors(node=on.node, epoch=1)
        mined = [tx["hash"].lower() for tx in transactions_of(on.anvil, on.node)]
    assert [str(anchor.tx_hash).lower() for anchor in anchored] == [replacement]
    assert recorded["tx"].lower() == replacement
    assert original not in mined
    assert proxy.prices[replacement] >= proxy.prices[original] * 9 // 8
