"""How long a transaction may spend in py-evm's pure-Python curve precompiles.

A transaction holds the chain's lock while it is mined and cannot be stopped half-way (its
result must not depend on the wall clock), so its gas is what bounds how long everyone else
waits. For opcodes that bound is a few seconds (a JUMP loop of 2^24 gas: about 3.7 s), but
py-evm runs the bn254 and BLS12-381 precompiles in py_ecc, 10 to 50 times slower a unit of
gas: one transaction of 2^24 gas of pairings held the chain for about three minutes, and
anvil answers it in milliseconds.

So this chain gives each transaction a budget for them, in the seconds their charges will
take at the rates measured below: deterministic (the same transaction on the same state
always spends the same), and large enough for what contracts verify in one transaction (a
Groth16 proof is 4 pairings, a BLS signature 2). A precompile whose charge would overspend
it fails as if it had run out of gas: its frame's gas is consumed and the caller sees a
failed call, as on any chain when a call is given too little gas. That is this chain's one
departure from Ethereum's rules, documented in docs/ledger.md.
"""

from __future__ import annotations

from eth.exceptions import OutOfGas
from eth.vm.forks.cancun.transaction_context import CancunTransactionContext
from eth.vm.forks.prague.computation import PragueComputation
from eth.vm.forks.prague.state import PragueState

SLOW_PRECOMPILE_SECONDS_PER_GAS = {
    bytes(19) + bytes([address]): seconds_per_gas
    for address, seconds_per_gas in (
        (0x07, 2.8e-6),  # bn254 multiplication
        (0x08, 9.4e-6),  # bn254 pairing: 0.25-0.53 s a pair
        (0x0C, 3.5e-6),  # BLS12-381 G1 MSM
        (0x0E, 9.8e-6),  # G2 MSM
        (0x0F, 10.8e-6),  # BLS12-381 pairing: 0.7-0.76 s a pair
        (0x10, 0.7e-6),  # map to G1
        (0x11, 5.9e-6),  # map to G2
    )
}
"""What py-evm's pure-Python precompiles take a unit of the gas they charge (the larger of
two runs on the 2-core development machine, one under load). The additions (150 to 600 gas)
never charge enough to matter; blake2f runs natively (``blake2b-py``), modexp in CPython's
``pow``."""

PRECOMPILE_CHECK_GAS = 1_000
"""Charges smaller than this are opcodes, or precompiles too quick to matter."""

TRANSACTION_PRECOMPILE_SECONDS = 4.0
"""A transaction's budget: what a JUMP loop of the largest transaction (2^24 gas) takes, so
no precompile holds the chain longer than opcodes can. 11 bn254 pairings (425,000 gas) or
10 BLS12-381 pairings fit."""


class BudgetedTransactionContext(CancunTransactionContext):
    """A transaction's context, carrying what its precompiles have spent of its budget."""

    precompile_seconds = 0.0


class BudgetedComputation(PragueComputation):
    """Takes each slow precompile's charge from its transaction's budget before it runs."""

    transaction_context: BudgetedTransactionContext

    def consume_gas(self, amount: int, reason: str) -> None:
        """py-evm's own ``consume_gas`` (a call to the gas meter) after the budget check,
        without the frame ``super()`` would add: it runs once per opcode."""
        if amount >= PRECOMPILE_CHECK_GAS:
            self.spend_precompile_budget(amount, reason)
        self._gas_meter.consume_gas(amount, reason)

    def spend_precompile_budget(self, amount: int, reason: str) -> float:
        """The seconds a charge of ``amount`` to this frame's precompile will take, taken
        from the transaction's budget; 0 for anything but a slow precompile, and for the
        charge py-evm makes of a failed frame's remaining gas (nothing runs for it).
        ``OutOfGas`` (the frame fails, its gas spent) when the budget does not hold them."""
        rate = SLOW_PRECOMPILE_SECONDS_PER_GAS.get(self.msg.code_address)
        if rate is None or self.is_error:
            return 0.0
        seconds = amount * rate
        context = self.transaction_context
        if context.precompile_seconds + seconds > TRANSACTION_PRECOMPILE_SECONDS:
            raise OutOfGas(
                f"{reason}: {amount} gas would take about {seconds:.1f} s, past the "
                f"{TRANSACTION_PRECOMPILE_SECONDS:g} s this chain gives a transaction's "
                f"curve precompiles ({context.precompile_seconds:.1f} s already spent)"
            )
        context.precompile_seconds += seconds
        return seconds


class BudgetedState(PragueState):
    """Prague's state, its transactions run with a precompile budget."""

    computation_class = BudgetedComputation
    transaction_context_class = BudgetedTransactionContext
