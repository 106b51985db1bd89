"""Where the contracts are, as the ledger service's ``GET /v1/contracts`` says."""

from __future__ import annotations

import pytest

from robocloud.ledger import ContractAddresses, ContractsUnavailableError

REGISTRY = "0x5B38Da6a701c568545dCfcB03FcB875f56beddC4"
ANCHOR_LOG = "0xAb8483F64d9C6d1EcF9b849Ae677dD3315835cb2"


def test_addresses_are_read_and_checksummed() -> None:
    body = {
        "chain_id": 1337,
        "contracts": {
            "Registry": {"address": REGISTRY.lower(), "abi": []},
            "AnchorLog": {"address": ANCHOR_LOG.lower(), "abi": []},
        },
    }
    assert ContractAddresses.from_service(body) == ContractAddresses(REGISTRY, ANCHOR_LOG)


@pytest.mark.parametrize(
    "body",
    [
        None,
        [],
        {"contracts": []},
        {"contracts": {"Registry": {"address": REGISTRY}}},
        {"contracts": {"Registry": REGISTRY, "AnchorLog": ANCHOR_LOG}},
    ],
)
def test_missing_addresses_are_a_clear_error(body: object) -> None:
    with pytest.raises(ContractsUnavailableError, match="lacks Registry or AnchorLog"):
        ContractAddresses.from_service(body)


def test_a_malformed_address_is_refused() -> None:
    body = {"contracts": {"Registry": {"address": "0x12"}, "AnchorLog": {"address": ANCHOR_LOG}}}
    with pytest.raises(ContractsUnavailableError, match="not an Ethereum address"):
        ContractAddresses.from_service(body)
