"""The chain's one departure from Ethereum's rules, beside anvil: a transaction's curve
precompiles have a budget in the seconds py-evm takes to run them (services/ledger/
precompile_budget.py). Within it a transaction is mined as anvil mines it; past it the
precompile fails as out of gas, where it used to hold the chain's lock for minutes."""

from __future__ import annotations

from tests.integration.services.ledger.conftest import Pair, call, deploying, mined, result
from tests.integration.services.ledger.test_bounded_calls import bn254_pairs
from tests.rawtx import RawTx

PAIRING = bytes(19) + b"\x08"
GAS = 700_000


def pairing_check(pairs: int) -> RawTx:
    """A transaction straight to the bn254 pairing precompile with ``2 * pairs`` pairs."""
    return RawTx(to=PAIRING, data=bytes.fromhex(bn254_pairs(pairs)[2:]), gas=GAS, max_fee=10**11)


def test_pairings_within_the_budget_are_mined_as_on_anvil(pair: Pair) -> None:
    """4 pairs (181,000 gas): a Groth16 proof's verification."""
    sender = pair.funded()
    receipts = []
    for url in pair.urls:
        tx_hash = result(
            url, "eth_sendRawTransaction", [pairing_check(2).sign(bytes(sender.account.key))]
        )
        receipts.append(mined(url, tx_hash))
    assert [receipt["status"] for receipt in receipts] == ["0x1", "0x1"]
    assert receipts[0]["gasUsed"] == receipts[1]["gasUsed"]


def test_pairings_past_the_budget_fail_as_out_of_gas_where_anvil_runs_them(pair: Pair) -> None:
    """12 pairs (453,000 gas, about 4.3 s in py_ecc, over the 4 s budget): anvil mines them
    with status 1 in milliseconds; py-evm took 4 to 6 s, and 2^24 gas of them about three
    minutes, with the chain's lock held throughout."""
    sender = pair.funded()
    ledger_hash = result(
        pair.ledger, "eth_sendRawTransaction", [pairing_check(6).sign(bytes(sender.account.key))]
    )
    receipt = mined(pair.ledger, ledger_hash)
    assert (receipt["status"], receipt["gasUsed"]) == ("0x0", hex(GAS))
    anvil_hash = result(
        pair.anvil, "eth_sendRawTransaction", [pairing_check(6).sign(bytes(sender.account.key))]
    )
    assert mined(pair.anvil, anvil_hash)["status"] == "0x1"
    called = {"to": "0x" + PAIRING.hex(), "data": bn254_pairs(6)}
    assert call(pair.ledger, "eth_call", [called, "latest"])["error"] == {
        "code": -32000,
        "message": "execution failed: OutOfGas ECPAIRING Precompile: 453000 gas would take "
        "about 4.3 s, past the 4 s this chain gives a transaction's curve precompiles (0.0 s "
        "already spent)",
    }


CALL_PAIRING = "602061400036600060085afa"
"""STATICCALL(GAS, 0x08, 0, CALLDATASIZE, 0x4000, 32): PUSH1 32, PUSH2 0x4000,
CALLDATASIZE, PUSH1 0, PUSH1 8, GAS, STATICCALL."""
TWICE = bytes.fromhex("366000600037" + CALL_PAIRING + "600055" + CALL_PAIRING + "600155" + "00")
"""Runtime code: copy the calldata, STATICCALL the pairing precompile with it twice (all the
gas each time), and store the two success flags in slots 0 and 1."""


def test_the_budget_is_the_transactions_across_its_calls(pair: Pair) -> None:
    """Each of two calls of 6 pairings (2.3 s) fits; both do not (4.7 s). The second call
    fails where anvil's succeeds; the transaction, which ignores it, is mined on both."""
    sender = pair.funded()
    contracts = pair.deploy(sender, deploying(TWICE))
    flags = []
    for url, contract in zip(pair.urls, contracts, strict=True):
        nonce = int(result(url, "eth_getTransactionCount", [sender.address, "latest"]), 16)
        tx = RawTx(
            nonce=nonce,
            to=bytes.fromhex(contract[2:]),
            data=bytes.fromhex(bn254_pairs(3)[2:]),
            gas=2_000_000,
            max_fee=10**11,
        )
        receipt = mined(
            url, result(url, "eth_sendRawTransaction", [tx.sign(bytes(sender.account.key))])
        )
        assert receipt["status"] == "0x1", url
        flags.append(
            [
                int(result(url, "eth_getStorageAt", [contract, hex(slot), "latest"]), 16)
                for slot in (0, 1)
            ]
        )
    assert flags == [[1, 0], [1, 1]]


def test_a_precompile_refusing_its_input_is_that_failure_not_a_timeout(pair: Pair) -> None:
    """py-evm charges a failed frame its remaining gas; the call's check took that charge
    for the precompile's own and answered every failed pairing "execution aborted (timeout
    = 5s)" at once, where anvil answers the precompile's error."""
    malformed = {"to": "0x" + PAIRING.hex(), "data": "0x" + "01" * 100}
    assert call(pair.ledger, "eth_call", [malformed, "latest"])["error"] == {
        "code": -32000,
        "message": "execution failed: VMError Invalid ECPAIRING parameters",
    }
    assert call(pair.anvil, "eth_call", [malformed, "latest"])["error"]["message"] == (
        "EVM error PrecompileError"
    )
