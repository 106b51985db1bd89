"""eth_feeHistory reports the tips actually paid, at the requested percentiles, and the blob
fields; the same transactions on the ledger and on anvil give the same rewards."""

from __future__ import annotations

import pytest

from tests.integration.services.ledger.conftest import Pair, call, mined, result
from tests.rawtx import RawTx

GWEI = 10**9


def test_rewards_are_the_tips_paid_on_both(pair: Pair) -> None:
    sender = pair.funded()
    histories = []
    for url in pair.urls:
        for nonce, tip in enumerate((1, 2, 3)):
            tx = RawTx(nonce=nonce, max_fee=100 * GWEI, max_priority_fee=tip * GWEI)
            tx_hash = result(url, "eth_sendRawTransaction", [tx.sign(bytes(sender.account.key))])
            assert mined(url, tx_hash)["status"] == "0x1"
        history = result(url, "eth_feeHistory", ["0x3", "latest", [0, 50, 99.5]])
        head = int(result(url, "eth_blockNumber", []), 16)
        assert history["oldestBlock"] == hex(head - 2)
        assert history["reward"] == [[hex(tip * GWEI)] * 3 for tip in (1, 2, 3)], url
        assert len(history["baseFeePerGas"]) == 4
        assert len(history["gasUsedRatio"]) == 3
        histories.append(history)
    ours, theirs = histories
    assert ours["reward"] == theirs["reward"]
    assert ours["baseFeePerBlobGas"] == theirs["baseFeePerBlobGas"] == ["0x1"] * 4
    assert ours["blobGasUsedRatio"] == theirs["blobGasUsedRatio"] == [0.0] * 3


def test_a_legacy_transaction_pays_its_price_above_the_base_fee(pair: Pair) -> None:
    sender = pair.funded()
    for url in pair.urls:
        tx = RawTx(kind=0, gas_price=7 * GWEI)
        tx_hash = result(url, "eth_sendRawTransaction", [tx.sign(bytes(sender.account.key))])
        receipt = mined(url, tx_hash)
        block = result(url, "eth_getBlockByNumber", [receipt["blockNumber"], False])
        history = result(url, "eth_feeHistory", ["0x1", receipt["blockNumber"], [50]])
        assert history["reward"] == [[hex(7 * GWEI - int(block["baseFeePerGas"], 16))]]


def test_without_percentiles_there_are_no_rewards_and_empty_blocks_pay_nothing(
    pair: Pair,
) -> None:
    history = result(pair.ledger, "eth_feeHistory", ["0x1", "0x0", [25, 75]])
    assert history["reward"] == [["0x0", "0x0"]]
    assert "reward" not in result(pair.ledger, "eth_feeHistory", ["0x2", "latest"])


@pytest.mark.parametrize("percentiles", [[101], [-1], [50, 10], ["50"], [True], list(range(101))])
def test_bad_percentiles_are_invalid_params(pair: Pair, percentiles: list[object]) -> None:
    error = call(pair.ledger, "eth_feeHistory", ["0x1", "latest", percentiles])["error"]
    assert error["code"] == -32602
    assert error["message"].startswith("invalid reward percentile")
