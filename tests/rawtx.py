"""Raw signed transactions with any field values, valid or not, for refusal tests.

eth-account refuses to sign some invalid transactions and normalises others; a node must be
tested with exactly the bytes a hostile or buggy client could send, so these are built from
RLP directly and signed with eth-keys.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import rlp
from eth_keys import keys
from eth_utils.crypto import keccak

SECPK1_N = 0xFFFFFFFFFFFFFFFFFFFFFFFFFFFFFFFEBAAEDCE6AF48A03BBFD25E8CD0364141


@dataclass(frozen=True)
class RawTx:
    """A transaction's fields; ``kind`` 0 (legacy, EIP-155), 1 (EIP-2930), 2 (EIP-1559) or 4
    (EIP-7702, with ``authorizations``: see ``authorization``)."""

    kind: int = 2
    chain_id: int = 1337
    nonce: int = 0
    gas: int = 21_000
    to: bytes = b"\x11" * 20
    value: int = 0
    data: bytes = b""
    gas_price: int = 2 * 10**9
    max_fee: int = 2 * 10**9
    max_priority_fee: int = 10**9
    access_list: list[Any] = field(default_factory=list)
    authorizations: list[Any] = field(default_factory=list)

    def unsigned_fields(self) -> list[Any]:
        if self.kind == 0:
            return [self.nonce, self.gas_price, self.gas, self.to, self.value, self.data]
        if self.kind == 1:
            return [
                self.chain_id, self.nonce, self.gas_price, self.gas, self.to, self.value,
                self.data, self.access_list,
            ]  # fmt: skip
        dynamic = [
            self.chain_id, self.nonce, self.max_priority_fee, self.max_fee, self.gas, self.to,
            self.value, self.data, self.access_list,
        ]  # fmt: skip
        return [*dynamic, self.authorizations] if self.kind == 4 else dynamic

    def sign(
        self,
        key: bytes,
        *,
        v: int | None = None,
        s_high: bool = False,
        r: int | None = None,
        s: int | None = None,
    ) -> str:
        """The raw transaction as 0x-hex; ``v``, ``r``, ``s`` and ``s_high`` forge the
        signature (``v`` is the y parity of a typed transaction)."""
        fields = self.unsigned_fields()
        if self.kind == 0:
            digest = keccak(rlp.encode([*fields, self.chain_id, 0, 0]))
        else:
            digest = keccak(bytes([self.kind]) + rlp.encode(fields))
        signature = keys.PrivateKey(key).sign_msg_hash(digest)
        parity, sig_r, sig_s = signature.v, signature.r, signature.s
        if s_high:
            sig_s, parity = SECPK1_N - sig_s, 1 - parity
        sig_r = sig_r if r is None else r
        sig_s = sig_s if s is None else s
        if self.kind == 0:
            legacy_v = self.chain_id * 2 + 35 + parity if v is None else v
            return "0x" + rlp.encode([*fields, legacy_v, sig_r, sig_s]).hex()
        parity = parity if v is None else v
        return "0x" + (bytes([self.kind]) + rlp.encode([*fields, parity, sig_r, sig_s])).hex()

    def but(self, **changes: Any) -> RawTx:
        return replace(self, **changes)


def authorization(key: bytes, address: bytes, nonce: int, chain_id: int = 1337) -> list[Any]:
    """An EIP-7702 authorization signed with ``key``: ``[chain_id, address, nonce, y_parity,
    r, s]``, its fields free to be forged by replacing items."""
    digest = keccak(b"\x05" + rlp.encode([chain_id, address, nonce]))
    signature = keys.PrivateKey(key).sign_msg_hash(digest)
    return [chain_id, address, nonce, signature.v, signature.r, signature.s]
