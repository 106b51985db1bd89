"""The pending pool: per-sender and total bounds, expiry, replacement, stale nonces."""

from __future__ import annotations

import pytest
from eth.abc import SignedTransactionAPI
from eth.vm.forks.prague import PragueVM

from robocloud.identity import Identity
from services.ledger.pool import PendingPool, PoolLimits
from services.ledger.refusals import ChainError
from tests.clock import Clock
from tests.rawtx import RawTx


def signed(
    identity: Identity, nonce: int, tip: int = 10**9, cap: int = 10**11
) -> SignedTransactionAPI:
    raw = RawTx(nonce=nonce, max_fee=cap, max_priority_fee=tip).sign(bytes(identity.account.key))
    transaction: SignedTransactionAPI = PragueVM.get_transaction_builder().decode(
        bytes.fromhex(raw[2:])
    )
    return transaction


def test_expired_transactions_leave_and_free_room() -> None:
    clock = Clock(0.0)
    pool = PendingPool(PoolLimits(max_per_sender=2, max_total=2, timeout_s=10), clock)
    sender = Identity.generate()
    pool.add(signed(sender, 1))
    pool.add(signed(sender, 2))
    with pytest.raises(ChainError, match="txpool is full"):
        pool.add(signed(sender, 3))
    clock.now = 11
    pool.add(signed(sender, 3))
    assert len(pool) == 1
    assert pool.take(bytes.fromhex(sender.address[2:]), 1) is None


def test_taking_a_nonce_drops_the_stale_ones_below_it() -> None:
    pool = PendingPool(PoolLimits())
    sender = Identity.generate()
    address = bytes.fromhex(sender.address[2:])
    for nonce in (1, 2, 4):
        pool.add(signed(sender, nonce))
    found = pool.take(address, 4)
    assert found is not None
    assert found.nonce == 4
    assert len(pool) == 0
    assert pool.waiting(address) == 0


def test_replacement_needs_ten_percent_more() -> None:
    pool = PendingPool(PoolLimits())
    sender = Identity.generate()
    pool.add(signed(sender, 1, tip=10**9))
    with pytest.raises(ChainError, match="replacement transaction underpriced"):
        pool.add(signed(sender, 1, tip=10**9 + 10**8 - 1))
    with pytest.raises(ChainError, match="already known"):
        pool.add(signed(sender, 1, tip=10**9))
    with pytest.raises(ChainError, match="replacement transaction underpriced"):
        pool.add(signed(sender, 1, tip=2 * 10**9))  # the fee cap must rise 10 % too
    pool.add(signed(sender, 1, tip=2 * 10**9, cap=2 * 10**11))
    assert len(pool) == 1


def test_a_transaction_is_found_by_hash_until_it_leaves() -> None:
    """``find`` answers the receipt polls of waiting transactions without the chain's lock,
    so it must forget each hash as its transaction leaves: replaced, taken, stale, expired."""
    clock = Clock(0.0)
    pool = PendingPool(PoolLimits(timeout_s=10), clock)
    sender = Identity.generate()
    address = bytes.fromhex(sender.address[2:])
    first, stale, taken = signed(sender, 1), signed(sender, 2), signed(sender, 3)
    for transaction in (first, stale, taken):
        pool.add(transaction)
    assert pool.find(stale.hash) is stale
    replacement = signed(sender, 1, tip=2 * 10**9, cap=2 * 10**11)
    pool.add(replacement)
    assert pool.find(first.hash) is None
    assert pool.find(replacement.hash) is replacement
    assert pool.take(address, 3) is taken
    assert [pool.find(t.hash) for t in (replacement, stale, taken)] == [None, None, None]
    late = signed(sender, 5)
    pool.add(late)
    clock.now = 11
    pool.expire()
    assert pool.find(late.hash) is None
    assert len(pool) == 0
