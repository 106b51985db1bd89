"""The precompiles py-evm can run natively do so."""

from __future__ import annotations

import hashlib
import struct

from eth.precompiles import blake2

BLAKE2B_IV = (
    0x6A09E667F3BCC908,
    0xBB67AE8584CAA73B,
    0x3C6EF372FE94F82B,
    0xA54FF53A5F1D36F1,
    0x510E527FADE682D1,
    0x9B05688C2B3E6C1F,
    0x1F83D9ABFB41BD6B,
    0x5BE0CD19137E2179,
)


def blake2f_input_hashing(message: bytes, rounds: int = 12) -> bytes:
    """EIP-152's input for the one compression of BLAKE2b-512 over a short ``message``: its
    output is then ``hashlib.blake2b(message)`` (EIP-152's fifth test vector for b"abc")."""
    state = (BLAKE2B_IV[0] ^ 0x01010040, *BLAKE2B_IV[1:])
    return (
        struct.pack(">I", rounds)
        + struct.pack("<8Q", *state)
        + message.ljust(128, b"\0")
        + struct.pack("<QQ", len(message), 0)
        + b"\x01"
    )


def test_blake2f_is_the_native_one_and_agrees_with_hashlib() -> None:
    """py-evm falls back to pure Python without a word when blake2b-py is missing: 15.5 us a
    round, so one transaction's 2^24 gas of rounds held the chain for 260 s (0.8 s native)."""
    assert blake2.blake2b_compress.__module__ == "blake2b.blake2b"
    parameters = blake2.extract_blake2b_parameters(blake2f_input_hashing(b"abc"))
    assert blake2.blake2b_compress(*parameters) == hashlib.blake2b(b"abc").digest()
