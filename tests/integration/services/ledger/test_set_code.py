"""EIP-7702 set-code transactions side by side with anvil: a delegated EOA keeps sending
transactions, a type-4 transaction shows its authorizations, and an authorization that
cannot even be decoded is invalid params, nothing mined."""

from __future__ import annotations

from typing import Any

import pytest

from robocloud.identity import Identity
from tests.integration.services.ledger.conftest import (
    Pair,
    Service,
    call,
    faucet,
    head,
    mined,
    result,
)
from tests.rawtx import RawTx, authorization

TARGET = b"\x22" * 20
SET_CODE = RawTx(kind=4, to=TARGET, gas=100_000, max_fee=10**11, max_priority_fee=10**9)


def nonce_of(url: str, identity: Identity) -> int:
    return int(result(url, "eth_getTransactionCount", [identity.address, "latest"]), 16)


def test_a_delegated_eoa_keeps_sending_transactions_as_on_anvil(pair: Pair) -> None:
    """The ledger refused every transaction from an EOA that had delegated ("sender not an
    eoa"): EIP-7702 amends EIP-3607 to let code that is a delegation designator send."""
    identity = pair.funded()
    key = bytes(identity.account.key)
    sender = bytes.fromhex(identity.address[2:])
    seen = []
    for url in pair.urls:
        # The sender's nonce moves before authorizations apply, so it signs nonce + 1.
        delegate = SET_CODE.but(to=sender, authorizations=[authorization(key, TARGET, 1)])
        tx_hash = result(url, "eth_sendRawTransaction", [delegate.sign(key)])
        receipt = mined(url, tx_hash)
        assert receipt["status"] == "0x1"
        assert receipt["type"] == "0x4"
        code = result(url, "eth_getCode", [identity.address, "latest"])
        assert code == "0xef0100" + TARGET.hex()
        transaction = result(url, "eth_getTransactionByHash", [tx_hash])
        assert nonce_of(url, identity) == 2
        plain = RawTx(nonce=2, to=b"\x33" * 20, value=1, max_fee=10**11)
        sent = result(url, "eth_sendRawTransaction", [plain.sign(key)])
        assert mined(url, sent)["status"] == "0x1"
        seen.append((transaction["authorizationList"], receipt["gasUsed"]))
    assert seen[0] == seen[1]
    assert seen[0][0] == [
        {
            "chainId": "0x539",
            "address": "0x" + TARGET.hex(),
            "nonce": "0x1",
            "yParity": seen[0][0][0]["yParity"],
            "r": seen[0][0][0]["r"],
            "s": seen[0][0][0]["s"],
        }
    ]


def forged(field: int, value: Any) -> Any:
    def build(key: bytes) -> RawTx:
        signed = authorization(key, TARGET, 0)
        signed[field] = value
        return SET_CODE.but(authorizations=[signed])

    return build


MALFORMED = {
    "chain-id-above-uint256": forged(0, 2**256),
    "address-empty": forged(1, b""),
    "address-19-bytes": forged(1, TARGET[:19]),
    "nonce-above-uint64": forged(2, 2**64),
    "r-above-uint256": forged(4, 2**256),
    "fields-missing": lambda key: SET_CODE.but(authorizations=[[1337, TARGET, 0]]),
    "creation": lambda key: SET_CODE.but(to=b"", authorizations=[authorization(key, TARGET, 1)]),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_set_code_transactions_are_invalid_params_on_both(pair: Pair, case: str) -> None:
    """Several of these were -32000 (py-evm's checks at mining time): anvil and geth cannot
    decode them."""
    identity = pair.funded()
    raw = MALFORMED[case](bytes(identity.account.key)).sign(bytes(identity.account.key))
    before = head(pair.service_url)
    errors = [call(url, "eth_sendRawTransaction", [raw])["error"] for url in pair.urls]
    assert errors[0]["code"] == errors[1]["code"] == -32602, errors
    assert errors[0]["message"].startswith("invalid raw transaction: "), errors
    assert head(pair.service_url) == before
    assert nonce_of(pair.ledger, identity) == 0


def test_an_empty_authorization_list_is_refused_as_geth_does(service: Service) -> None:
    """anvil 1.7.1 answers it with a hash and never mines it; geth refuses it."""
    identity = Identity.generate()
    assert faucet(service.url, identity).status_code == 200
    before = head(service.url)
    raw = SET_CODE.sign(bytes(identity.account.key))
    answer = call(f"{service.url}/rpc", "eth_sendRawTransaction", [raw])
    assert answer["error"] == {
        "code": -32000,
        "message": "EIP-7702 transaction with empty auth list",
    }
    assert head(service.url) == before
