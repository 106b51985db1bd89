"""What blocks charged and what their transactions paid, as ``eth_feeHistory`` reports it.

The tips at a percentile are geth's: a block's transactions sorted by the tip they actually
paid (``effective gas price - base fee``), each weighing the gas it used; the tip at
percentile p is that of the transaction in which the first p % of the block's gas falls. An
empty block reports zeros.
"""

from __future__ import annotations

from eth._utils.calculations import fake_exponential
from eth.abc import BlockAPI, BlockHeaderAPI, ReceiptAPI
from eth.vm.forks.cancun.constants import MIN_BLOB_BASE_FEE
from eth.vm.forks.prague.constants import (
    BLOB_BASE_FEE_UPDATE_FRACTION_PRAGUE,
    MAX_BLOB_GAS_PER_BLOCK,
)

from services.ledger.chain import gas_used_by
from services.ledger.encoding import base_fee, effective_gas_price


def tips_paid(block: BlockAPI, receipts: tuple[ReceiptAPI, ...]) -> list[tuple[int, int]]:
    """Each transaction's ``(tip paid per gas, gas used)``, cheapest first."""
    fee = base_fee(block.header)
    paid = [
        (effective_gas_price(tx, fee) - fee, gas_used_by(receipts, index))
        for index, tx in enumerate(block.transactions)
    ]
    return sorted(paid)


def rewards(paid: list[tuple[int, int]], percentiles: list[float]) -> list[int]:
    """The tip at each percentile of the block's gas (geth's ``processBlock``)."""
    if not paid:
        return [0] * len(percentiles)
    total = sum(gas for _, gas in paid)
    answer = []
    index, cumulative = 0, paid[0][1]
    for percentile in percentiles:
        threshold = total * percentile / 100
        while cumulative < threshold and index < len(paid) - 1:
            index += 1
            cumulative += paid[index][1]
        answer.append(paid[index][0])
    return answer


def blob_base_fee(header: BlockHeaderAPI) -> int:
    excess = int(getattr(header, "excess_blob_gas", 0) or 0)
    return int(fake_exponential(MIN_BLOB_BASE_FEE, excess, BLOB_BASE_FEE_UPDATE_FRACTION_PRAGUE))


def blob_gas_used_ratio(header: BlockHeaderAPI) -> float:
    return int(getattr(header, "blob_gas_used", 0) or 0) / MAX_BLOB_GAS_PER_BLOCK
