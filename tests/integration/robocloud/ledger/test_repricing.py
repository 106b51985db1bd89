"""A saved transaction still pending past the receipt timeout, as one whose gas price fell
behind a public chain's base fee stays: resumed, it is replaced by the same call on the same
nonce at a higher price, saved before it is sent, so that one of the two is mined and the
storage node's anchor or advertise is not stuck behind it for ever.

Against anvil with automatic mining off: the transaction stays pending until the test mines a
block (the ledger service mines every transaction at once, so it cannot hold one pending)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from robocloud.identity import Identity
from robocloud.ledger import JsonRpcClient, SignedTransaction
from robocloud.ledger.errors import FeeLimitError, TransactionTimeoutError
from robocloud.ledger.transactions import FeeLimits, Transactor, quantity
from tests.integration.robocloud.ledger.nodes import ethereum_node, fund

DEAD = "0x000000000000000000000000000000000000dEaD"
CALL = bytes.fromhex("c0ffee")


@pytest.fixture
def unmined(tmp_path: Path) -> Iterator[JsonRpcClient]:
    with (
        ethereum_node(tmp_path / "anvil.log", extra=["--no-mining"]) as url,
        JsonRpcClient(url) as rpc,
    ):
        yield rpc


def stuck(
    rpc: JsonRpcClient, limits: FeeLimits | None = None
) -> tuple[Transactor, list[SignedTransaction]]:
    """A robot's call sent and saved, its wait timed out: what the next attempt resumes."""
    transactor = Transactor(
        rpc, fund(rpc, Identity.generate()), receipt_timeout_s=1.0, limits=limits
    )
    saved: list[SignedTransaction] = []
    with pytest.raises(TransactionTimeoutError):
        transactor.send(DEAD, CALL, gas=30_000, before_send=saved.append)
    return transactor, saved


def mine_once_replaced(rpc: JsonRpcClient, saved: list[SignedTransaction]) -> threading.Thread:
    """Mine one block as soon as the node holds the replacement. Mined once it was saved, the
    block took the original on a loaded machine, the replacement not yet sent (the race
    ``test_the_original_mined_between_saving_and_sending_its_replacement_is_the_answer``
    makes on purpose)."""

    def sent() -> bool:
        return len(saved) > 1 and (
            rpc.request("eth_getTransactionByHash", [saved[1].tx_hash]) is not None
        )

    def mine() -> None:
        deadline = time.monotonic() + 30
        while not sent() and time.monotonic() < deadline:
            time.sleep(0.05)
        rpc.request("evm_mine", [])

    miner = threading.Thread(target=mine)
    miner.start()
    return miner


def price(rpc: JsonRpcClient, signed: SignedTransaction) -> int:
    return quantity(rpc.request("eth_getTransactionByHash", [signed.tx_hash])["gasPrice"])


def test_a_stuck_transaction_is_replaced_and_the_replacement_mined(
    unmined: JsonRpcClient,
) -> None:
    transactor, saved = stuck(unmined)
    original_price = price(unmined, saved[0])
    miner = mine_once_replaced(unmined, saved)
    receipt = transactor.resume(saved[0], before_send=saved.append)
    miner.join()
    original, replacement = saved
    assert receipt is not None
    assert receipt.status == 1
    assert receipt.tx_hash == replacement.tx_hash
    assert replacement.nonce == original.nonce
    assert price(unmined, replacement) >= original_price * 9 // 8
    assert unmined.request("eth_getTransactionReceipt", [original.tx_hash]) is None
    sender = transactor.identity.address
    assert quantity(unmined.request("eth_getTransactionCount", [sender, "latest"])) == 1
    assert transactor.resume(original) is None  # its nonce went to the replacement


def test_the_original_mined_between_saving_and_sending_its_replacement_is_the_answer(
    unmined: JsonRpcClient,
) -> None:
    """The original is mined while its replacement is saved: the node refuses the replacement
    ("nonce too low"), and the call did happen, by the original. That refusal was raised to
    the caller as a failed call."""
    transactor, saved = stuck(unmined)

    def save_while_a_block_is_mined(replacement: SignedTransaction) -> None:
        saved.append(replacement)
        unmined.request("evm_mine", [])

    receipt = transactor.resume(saved[0], before_send=save_while_a_block_is_mined)
    original, replacement = saved
    assert receipt is not None
    assert (receipt.tx_hash, receipt.status) == (original.tx_hash, 1)
    assert unmined.request("eth_getTransactionByHash", [replacement.tx_hash]) is None


def test_without_a_place_to_save_it_no_replacement_is_signed(unmined: JsonRpcClient) -> None:
    """The caller must be able to save what it sends: a replacement it could not find after
    a crash would leave it waiting on the original."""
    transactor, saved = stuck(unmined)
    with pytest.raises(TransactionTimeoutError):
        transactor.resume(saved[0])
    pending = unmined.request("eth_getTransactionCount", [transactor.identity.address, "pending"])
    assert quantity(pending) == 1
    assert unmined.request("eth_getTransactionByHash", [saved[0].tx_hash]) is not None


def test_a_replacement_over_the_fee_limit_is_refused_before_signing(
    unmined: JsonRpcClient,
) -> None:
    node_price = quantity(unmined.request("eth_gasPrice", []))
    transactor, saved = stuck(unmined, FeeLimits(max_gas=100_000, max_fee_per_gas=node_price))
    with pytest.raises(FeeLimitError):
        transactor.resume(saved[0], before_send=saved.append)
    assert len(saved) == 1
    assert unmined.request("eth_getTransactionByHash", [saved[0].tx_hash]) is not None
