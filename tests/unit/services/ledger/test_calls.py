"""Calls on kept states: each thread reuses the state of the block its last call ran at, so
these check that a call leaves nothing behind for the next (storage, transient storage),
whether it returned, reverted, ran out of its time or of its budget, and that a new head or
an older block is seen as it is."""

from __future__ import annotations

from pathlib import Path

import pytest

from robocloud.identity import Identity
from services.ledger.calls import CallLimits, OverBudget
from services.ledger.chain import CallRequest, ChainError, EmbeddedChain, Reverted
from services.ledger.contracts import create_address, send_as

# Counts its runs in storage slot 0 and in transient slot 0 and answers both counts from
# before the increment; with calldata it then loops forever, and with one byte 0xff it
# reverts instead.
COUNTER = bytes.fromhex(
    "5f5480600101 5f55 5f52 5f5c80600101 5f5d 602052"  # count: mem[0] slot 0, mem[32] transient
    "3615602957"  # no calldata: jump to return
    "5f35 60f8 1c 60ff 14 602e57"  # calldata[0] == 0xff: jump to revert
    "5b602556"  # loop forever
    "5b60405ff3"  # return both counts
    "5b5f5ffd".replace(" ", "")  # revert
)


def deploying(runtime: bytes) -> bytes:
    """Init code that returns ``runtime`` (under 256 bytes) as the contract's code."""
    return bytes.fromhex(f"60{len(runtime):02x}80600b6000396000f3") + runtime


@pytest.fixture
def counter(tmp_path: Path) -> tuple[EmbeddedChain, bytes, Identity]:
    owner = Identity.generate()
    genesis = {
        bytes.fromhex(owner.address[2:]): {
            "balance": 10**24,
            "nonce": 0,
            "code": b"",
            "storage": {},
        }
    }
    chain = EmbeddedChain(tmp_path / "chain.sqlite", genesis, call_limits=CallLimits(timeout_s=0.2))
    send_as(chain, owner, None, deploying(COUNTER), gas=200_000)
    return chain, bytes.fromhex(create_address(owner.address, 0)[2:]), owner


def counts(chain: EmbeddedChain, address: bytes, tag: int | str = "latest") -> tuple[int, int]:
    answer = chain.call(CallRequest(sender=b"\x00" * 20, to=address), tag)
    return int.from_bytes(answer[:32], "big"), int.from_bytes(answer[32:], "big")


def test_a_call_leaves_nothing_for_the_next(counter: tuple[EmbeddedChain, bytes, Identity]) -> None:
    chain, address, _ = counter
    assert [counts(chain, address) for _ in range(5)] == [(0, 0)] * 5
    chain.close()


def test_a_new_head_is_seen_and_an_older_block_still_is(
    counter: tuple[EmbeddedChain, bytes, Identity],
) -> None:
    chain, address, owner = counter
    deployed = chain.head().block_number
    assert counts(chain, address) == (0, 0)
    send_as(chain, owner, create_address(owner.address, 0), gas=100_000)
    assert counts(chain, address) == (1, 0)
    assert counts(chain, address, deployed) == (0, 0)
    assert counts(chain, address) == (1, 0)
    chain.close()


def test_reverted_aborted_and_over_budget_calls_leave_nothing(
    counter: tuple[EmbeddedChain, bytes, Identity],
) -> None:
    chain, address, _ = counter
    assert counts(chain, address) == (0, 0)
    with pytest.raises(Reverted):
        chain.call(CallRequest(sender=b"\x00" * 20, to=address, data=b"\xff"), "latest")
    assert counts(chain, address) == (0, 0)
    looping = CallRequest(sender=b"\x00" * 20, to=address, data=b"\x01")
    with pytest.raises(ChainError, match=r"execution aborted \(timeout = 0.2s\)"):
        chain.call(looping, "latest")
    assert counts(chain, address) == (0, 0)
    with pytest.raises(OverBudget):
        chain.call(looping, "latest", budget_s=0.01)
    assert counts(chain, address) == (0, 0)
    chain.close()


def test_a_call_that_runs_out_of_gas_says_so(
    counter: tuple[EmbeddedChain, bytes, Identity],
) -> None:
    """A call pays no fee, so however much gas it burns, the coinbase is not charged for it."""
    chain, address, _ = counter
    looping = CallRequest(sender=b"\x00" * 20, to=address, data=b"\x01", gas=300_000)
    with pytest.raises(ChainError, match="OutOfGas"):
        chain.call(looping, "latest", budget_s=60)
    assert counts(chain, address) == (0, 0)
    chain.close()
