"""robocloud's contracts on the embedded chain: artifacts, deployment, and where they live.

Deployment is idempotent without any bookkeeping that could disagree with the chain: the
admin's first two transactions create Registry and AnchorLog, so their addresses follow from
the admin's address alone (nonces 0 and 1). A start that finds the admin's nonce below two
sends what is missing; a crash between the two transactions is therefore harmless.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import rlp
from eth_utils.address import to_checksum_address
from eth_utils.crypto import keccak

from robocloud.identity import Identity
from robocloud.ledger.abi import ContractAbi
from robocloud.ledger.models import RegistrationMode
from services.ledger.chain import CallRequest, ChainError, EmbeddedChain

ARTIFACTS = Path(__file__).resolve().parents[2] / "contracts" / "build"
CONTRACT_NAMES = ("Registry", "AnchorLog")
DEPLOY_GAS = 5_000_000
PRIORITY_FEE_WEI = 10**9


@dataclass(frozen=True)
class Deployment:
    """Where the contracts are and what they look like, as ``GET /v1/contracts`` serves it."""

    registry: str
    anchor_log: str

    def addresses(self) -> dict[str, str]:
        return {"Registry": self.registry, "AnchorLog": self.anchor_log}

    def describe(self, chain_id: int) -> dict[str, Any]:
        contracts = {
            name: {"address": address, "abi": artifact(name)["abi"]}
            for name, address in self.addresses().items()
        }
        return {"contracts": contracts, "chain_id": chain_id}


def artifact(name: str) -> dict[str, Any]:
    loaded: dict[str, Any] = json.loads((ARTIFACTS / f"{name}.json").read_text())
    return loaded


def create_address(sender: str, nonce: int) -> str:
    """The address of the contract ``sender`` creates with its ``nonce``-th transaction."""
    encoded = rlp.encode([bytes.fromhex(sender[2:]), nonce])
    return str(to_checksum_address(keccak(encoded)[12:]))


def send_as(
    chain: EmbeddedChain,
    identity: Identity,
    to: str | None,
    data: bytes = b"",
    *,
    value: int = 0,
    gas: int = 21_000,
) -> bytes:
    """Sign a transaction with an operator key and mine it; its hash.

    Under the chain's lock from the nonce to the send: two faucet requests at once read the
    same pending nonce, and the second one's transaction was refused ("nonce too low").
    """
    with chain.exclusive():
        transaction: dict[str, Any] = {
            "chainId": chain.chain_id,
            "nonce": chain.nonce(bytes.fromhex(identity.address[2:]), "pending"),
            "gas": gas,
            "gasPrice": chain.base_fee() + PRIORITY_FEE_WEI,
            "data": data,
            "value": value,
        }
        if to is not None:
            transaction["to"] = to
        signed = identity.account.sign_transaction(transaction)
        return chain.send_raw_transaction(bytes(signed.raw_transaction)).hash


def deploy(chain: EmbeddedChain, admin: Identity) -> Deployment:
    """Deploy whatever of Registry and AnchorLog is missing; their addresses either way."""
    deployment = Deployment(create_address(admin.address, 0), create_address(admin.address, 1))
    sender = bytes.fromhex(admin.address[2:])
    if chain.nonce(sender, "latest") == 0:
        send_as(chain, admin, None, _creation("Registry"), gas=DEPLOY_GAS)
    if chain.nonce(sender, "latest") == 1:
        arguments = ContractAbi("AnchorLog", artifact("AnchorLog")["abi"]).encode_constructor(
            deployment.registry
        )
        send_as(chain, admin, None, _creation("AnchorLog") + arguments, gas=DEPLOY_GAS)
    for name, address in deployment.addresses().items():
        if not chain.code(bytes.fromhex(address[2:]), "latest"):
            raise ChainError(f"{name} has no code at {address}: its deployment failed")
    return deployment


class RegistrationModeConflict(Exception):
    """The Registry's registration mode is not the configured one, and this ledger does not
    hold the Registry's admin key to change it: running anyway would misstate who may write."""

    def __init__(self, registry: str, current: RegistrationMode, wanted: RegistrationMode) -> None:
        super().__init__(
            f"the Registry at {registry} is in the {current.name.lower()} registration mode, "
            f"but ROBOCLOUD_LEDGER_REGISTRATION_MODE is {wanted.name.lower()}, and this ledger "
            "does not hold the Registry's admin key: set the setting to the chain's mode, or "
            f"have the admin run `robocloud admin mode {wanted.name.lower()}`"
        )
        self.registry = registry
        self.current = current
        self.wanted = wanted


def must_switch_mode(
    registry: str,
    current: RegistrationMode,
    wanted: RegistrationMode,
    registry_admin: str,
    operator_admin: str | None,
) -> bool:
    """Whether the operator must switch the Registry from ``current`` to ``wanted``.

    ``ROBOCLOUD_LEDGER_REGISTRATION_MODE`` states the mode the deployment runs in. A ledger
    holding the Registry's admin key makes it so at every start; one that does not (attached
    to another operator's contracts, or after ``transferAdmin``) cannot, and refuses to start
    rather than serve a deployment whose registrations mean less than its operator believes.
    """
    if current is wanted:
        return False
    if operator_admin is None or operator_admin.lower() != registry_admin.lower():
        raise RegistrationModeConflict(registry, current, wanted)
    return True


def apply_registration_mode(
    chain: EmbeddedChain, admin: Identity, deployment: Deployment, mode: RegistrationMode
) -> bool:
    """Make the Registry's registration mode ``mode``; whether a transaction was needed.

    Requests pending when the mode switches to Open stay pending until a registrar decides.
    """
    registry = ContractAbi("Registry", artifact("Registry")["abi"])
    target = bytes.fromhex(deployment.registry[2:])

    def read(function: str) -> Any:
        request = CallRequest(sender=b"\x00" * 20, to=target, data=registry.encode_call(function))
        return registry.decode_output(function, chain.call(request, "latest"))[0]

    current = RegistrationMode(read("registrationMode"))
    if not must_switch_mode(deployment.registry, current, mode, read("admin"), admin.address):
        return False
    data = registry.encode_call("setRegistrationMode", mode.value)
    send_as(chain, admin, deployment.registry, data, gas=100_000)
    if RegistrationMode(read("registrationMode")) is not mode:
        raise ChainError(f"setting the Registry's registration mode to {mode.name.lower()} failed")
    return True


def _creation(name: str) -> bytes:
    return bytes.fromhex(str(artifact(name)["bytecode"]).removeprefix("0x"))
