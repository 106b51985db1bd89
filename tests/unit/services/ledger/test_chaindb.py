"""The development chain reopens where it was: same head hash, same state, even after kill -9."""

from __future__ import annotations

import textwrap
import time
from pathlib import Path

from eth_account import Account
from eth_tester.backends.pyevm.main import get_default_account_keys

from services.ledger.chaindb import CHAIN_ID, DevChain, open_chain
from tests.unit.services.ledger.crash import acknowledged_before_kill

RECIPIENT = bytes.fromhex("11" * 20)


def transfer(chain: DevChain, nonce: int, value: int = 1) -> None:
    key = get_default_account_keys(1)[0].to_bytes()
    raw = Account.sign_transaction(
        {
            "to": "0x" + RECIPIENT.hex(),
            "value": value,
            "gas": 21_000,
            "gasPrice": 10**10,
            "nonce": nonce,
            "chainId": CHAIN_ID,
        },
        key,
    ).raw_transaction
    chain.apply_transaction(chain.get_vm().get_transaction_builder().decode(raw))
    chain.mine_block()


def test_a_reopened_chain_has_the_same_head_and_state(tmp_path: Path) -> None:
    chain, db = open_chain(tmp_path / "chain.sqlite")
    genesis = chain.get_canonical_head().hash
    for nonce in range(3):
        transfer(chain, nonce, value=5)
    head = chain.get_canonical_head()
    db.close()
    reopened, db = open_chain(tmp_path / "chain.sqlite")
    assert reopened.get_canonical_head() == head
    assert reopened.get_canonical_block_header_by_number(0).hash == genesis
    assert reopened.get_vm().state.get_balance(RECIPIENT) == 15
    assert reopened.chain_id == CHAIN_ID
    transfer(reopened, 3)
    assert reopened.get_canonical_head().block_number == head.block_number + 1
    db.close()


def test_two_new_chains_share_one_genesis(tmp_path: Path) -> None:
    """Even a second apart: the genesis took eth-tester's clock, and this test failed
    whenever the two chains were created on either side of a second's boundary."""
    first, db1 = open_chain(tmp_path / "a.sqlite")
    time.sleep(1.05)
    second, db2 = open_chain(tmp_path / "b.sqlite")
    assert first.get_canonical_head().hash == second.get_canonical_head().hash
    db1.close()
    db2.close()


MINER = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from services.ledger.chaindb import open_chain
    from tests.unit.services.ledger.test_chaindb import transfer
    chain, _ = open_chain(Path(sys.argv[1]))
    for nonce in range(1000):
        transfer(chain, nonce)
        print(chain.get_canonical_head().hash.hex(), flush=True)
    """
)


def test_kill_9_loses_no_acknowledged_block(tmp_path: Path) -> None:
    path = tmp_path / "chain.sqlite"
    acknowledged = acknowledged_before_kill(MINER, path, 5)
    chain, db = open_chain(path)
    head = chain.get_canonical_head()
    assert head.block_number >= 5
    assert chain.get_canonical_block_header_by_number(5).hash.hex() == acknowledged[-1]
    db.close()
