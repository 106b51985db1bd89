"""Rules that need a state no public chain request can produce: a key whose address holds
code (EIP-3607), and each rule's place before anything is stored."""

from __future__ import annotations

from pathlib import Path

import pytest
from eth_utils.crypto import keccak

from robocloud.identity import Identity
from services.ledger.chain import ChainError, EmbeddedChain
from services.ledger.validation import floor_data_gas
from tests.rawtx import RawTx

CODE = bytes.fromhex("5f5ff3")


def test_a_sender_with_code_is_refused_as_geth_does(tmp_path: Path) -> None:
    """EIP-3607: an address that holds code cannot have sent a signed transaction."""
    owner = Identity.generate()
    address = bytes.fromhex(owner.address[2:])
    genesis = {address: {"balance": 10**20, "nonce": 0, "code": CODE, "storage": {}}}
    chain = EmbeddedChain(tmp_path / "chain.sqlite", genesis)
    try:
        head = chain.head()
        raw = RawTx(max_fee=10**11).sign(bytes(owner.account.key))
        with pytest.raises(ChainError) as refused:
            chain.send_raw_transaction(bytes.fromhex(raw[2:]))
        assert refused.value.message == (
            f"sender not an eoa: address {owner.address.lower()}, codehash: 0x{keccak(CODE).hex()}"
        )
        assert chain.head() == head
        assert chain.nonce(address, "latest") == 0
    finally:
        chain.close()


@pytest.mark.parametrize(
    ("data", "floor"), [(b"", 21_000), (b"\x00" * 10, 21_100), (b"\x01" * 10, 21_400)]
)
def test_the_calldata_floor_counts_tokens_as_eip_7623_does(data: bytes, floor: int) -> None:
    assert floor_data_gas(data) == floor
