"""Helpers for contract tests: artifacts, deployment, and revert assertions on eth-tester."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from eth_tester.exceptions import TransactionFailed
from web3 import EthereumTesterProvider, Web3
from web3.contract import Contract
from web3.contract.contract import ContractFunction
from web3.logs import DISCARD

BUILD_DIR = Path(__file__).resolve().parents[3] / "contracts" / "build"


def load_artifact(name: str) -> dict[str, Any]:
    artifact: dict[str, Any] = json.loads((BUILD_DIR / f"{name}.json").read_text())
    return artifact


def deploy(w3: Web3, name: str, sender: str, *args: object) -> Contract:
    artifact = load_artifact(name)
    factory = w3.eth.contract(abi=artifact["abi"], bytecode=artifact["bytecode"])
    receipt = w3.eth.wait_for_transaction_receipt(
        factory.constructor(*args).transact({"from": sender})
    )
    assert receipt["status"] == 1
    return w3.eth.contract(address=receipt["contractAddress"], abi=artifact["abi"])


@dataclass
class Chain:
    """The chain, its accounts and the deployed contracts; `admin` deployed both."""

    w3: Web3
    registry: Contract
    anchor_log: Contract
    admin: str
    robot: str
    other: str
    node: str

    def send(self, call: ContractFunction, sender: str) -> Any:
        """Mine `call` from `sender` and return its receipt, asserting it succeeded."""
        receipt = self.w3.eth.wait_for_transaction_receipt(call.transact({"from": sender}))
        assert receipt["status"] == 1
        return receipt

    def assert_reverts(self, call: ContractFunction, sender: str, reason: str) -> None:
        """Check the decoded reason of `eth_call`, then that a mined transaction reverts too.

        The mined transaction carries an explicit gas limit so it skips estimation (which would
        fail first) and reaches the chain, where it must end with status 0.
        """
        with pytest.raises(TransactionFailed) as raised:
            call.call({"from": sender})
        assert str(raised.value) == f"execution reverted: {reason}"
        tx_hash = call.transact({"from": sender, "gas": 1_000_000})
        assert self.w3.eth.get_transaction_receipt(tx_hash)["status"] == 0

    def events(self, contract: Contract, event: str, receipt: Any) -> list[dict[str, Any]]:
        """The receipt's ``event`` logs; logs of the receipt's other events are left out."""
        logs = contract.events[event]().process_receipt(receipt, errors=DISCARD)
        return [dict(log["args"]) for log in logs]

    def timestamp(self, receipt: Any) -> int:
        return int(self.w3.eth.get_block(receipt["blockNumber"])["timestamp"])


def new_chain() -> Chain:
    """A fresh in-process chain with Registry and AnchorLog deployed by its first account."""
    w3 = Web3(EthereumTesterProvider())
    admin, robot, other, node = w3.eth.accounts[:4]
    registry = deploy(w3, "Registry", admin)
    anchor_log = deploy(w3, "AnchorLog", admin, registry.address)
    return Chain(w3, registry, anchor_log, admin, robot, other, node)
