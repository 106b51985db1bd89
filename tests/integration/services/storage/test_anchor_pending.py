"""A storage node behind an external node (anvil), killed (SIGKILL) while its
``AnchorLog.anchor`` transaction is still pending: the restarted anchorer anchors the epoch
once, records the transaction that was mined, and goes on with the next epochs.

Real anvil, ledger (fronting anvil), cas and storage processes; the storage node reaches the
ledger through a forwarding proxy. On the first anchor transaction the proxy stops anvil's
mining, forwards it (anvil keeps it pending) and kills the node. On the next anchor
transaction it forwards it, then mines. anvil estimates gas on its pending block, where the
pending anchor already holds the epoch; geth estimates on the latest block, where it does not:
the proxy asks for ``latest`` in the second case.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import httpx
import pytest

from robocloud.identity import Identity
from robocloud.ledger import JsonRpcClient, Ledger, LedgerService
from tests.conftest import ServiceFactory
from tests.integration.services.storage.counter import write_counter_records
from tests.integration.services.storage.ledger_proxy import (
    LedgerProxy,
    anchoring_on_anvil,
    rpc_calls,
    selector,
    sends,
)
from tests.integration.services.storage.test_anchoring import node_state
from tests.procs import ServiceProcess
from tests.scripted_http import Exchange, Reply
from tests.waiting import wait_for

ANCHOR = selector("AnchorLog", "anchor")


def estimating_on(body: bytes, block: str) -> bytes:
    """``body`` with ``block`` added to each ``eth_estimateGas`` call that names none."""
    calls = rpc_calls(body)
    estimates = [
        call
        for call in calls
        if isinstance(call, dict)
        and call.get("method") == "eth_estimateGas"
        and isinstance(call.get("params"), list)
        and len(call["params"]) == 1
    ]
    if not estimates:
        return body
    for call in estimates:
        call["params"].append(block)
    return json.dumps(calls if body.lstrip().startswith(b"[") else calls[0]).encode()


class KillWhileAnchorPending(LedgerProxy):
    """A proxy script: the first anchor transaction reaches anvil with mining stopped, and the
    storage node is killed before any answer; the next one is forwarded, then mined.
    ``estimate_on`` is the block asked for in the node's gas estimates (None: anvil's own)."""

    def __init__(
        self, ledger: ServiceProcess, anvil: JsonRpcClient, estimate_on: str | None
    ) -> None:
        super().__init__(ledger)
        self.anvil = anvil
        self.estimate_on = estimate_on
        self.anchors = 0
        self.pending_tx: str | None = None

    def __call__(self, exchange: Exchange) -> Reply:
        if self.estimate_on is not None:
            exchange = replace(exchange, body=estimating_on(exchange.body, self.estimate_on))
        with self.lock:
            anchor = exchange.method == "POST" and sends(exchange.body, ANCHOR)
            self.anchors += anchor
            number = self.anchors if anchor else 0
        if number == 1:
            self.anvil.request("evm_setAutomine", [False])
        answer = self.forward(exchange)
        if number == 1:
            self.pending_tx = str(answer.json()["result"]).lower()
            return self.kill_storage()
        if number == 2:
            self.anvil.request("evm_setAutomine", [True])
            self.anvil.request("evm_mine", [])
        return self.answer(answer)


def wait_anchored(storage: ServiceProcess, epoch: int, what: str) -> None:
    """Wait until ``epoch`` is anchored; a timeout names the node's last anchoring error."""
    try:
        wait_for(lambda: node_state(storage)["last_anchored_epoch"] >= epoch, what, 60)
    except AssertionError as exc:
        raise AssertionError(f"{exc}: {node_state(storage)['anchor_error']}") from None


def transactions_of(anvil: JsonRpcClient, address: str) -> list[dict[str, Any]]:
    """Every mined transaction sent by ``address``, oldest first."""
    latest = int(anvil.request("eth_blockNumber", []), 16)
    found = []
    for number in range(latest + 1):
        block = anvil.request("eth_getBlockByNumber", [hex(number), True])
        found += [tx for tx in block["transactions"] if tx["from"].lower() == address.lower()]
    return found


@pytest.mark.parametrize(
    "estimate_on", [None, "latest"], ids=["estimates-on-pending", "estimates-on-latest"]
)
def test_kill_9_while_the_anchor_is_pending_anchors_the_epoch_once(
    service_factory: ServiceFactory, tmp_path: Path, estimate_on: str | None
) -> None:
    """The restarted anchorer found no anchor of the epoch (``anchorAt`` reads the latest
    block) and made another: refused by a gas estimate on the pending block (anvil) until the
    pending one was mined, or, estimated on the latest (geth), signed with the next nonce and
    reverted ("AnchorLog: epoch not increasing") once the first was mined."""
    with anchoring_on_anvil(
        lambda ledger, anvil: KillWhileAnchorPending(ledger, anvil, estimate_on),
        service_factory,
        tmp_path,
        {},
    ) as (proxy, on):
        storage = on.storage
        writer = Identity.generate()
        write_counter_records(storage, writer, 0, 40)
        proxy.wait_killed("the storage node to send its anchor transaction")

        storage.start()
        wait_anchored(storage, 1, "the pending epoch anchored after the restart")
        last = int(node_state(storage)["last_epoch"])
        write_counter_records(storage, writer, 40, 60)
        wait_anchored(storage, last + 1, "the next epoch anchored")
        recorded = httpx.get(f"{storage.url}/v1/epochs/1", timeout=10).json()["anchor"]

        with LedgerService(on.ledger.url) as service:
            addresses = service.contracts()
        with Ledger(JsonRpcClient(on.anvil_url), addresses) as chain:
            anchored = chain.anchors(node=on.node, epoch=1)
        sent = transactions_of(on.anvil, on.node)
        reverted = [
            tx["hash"]
            for tx in sent
            if on.anvil.request("eth_getTransactionReceipt", [tx["hash"]])["status"] != "0x1"
        ]
        nonce = int(on.anvil.request("eth_getTransactionCount", [on.node, "pending"]), 16)
    assert [str(anchor.tx_hash).lower() for anchor in anchored] == [proxy.pending_tx]
    assert recorded["tx"].lower() == proxy.pending_tx
    assert reverted == []
    assert nonce == len(sent)
