"""One anvil node and one deployment of the contracts per module; fresh robots per test."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from robocloud.identity import Identity
from robocloud.ledger import ContractAddresses, JsonRpcClient, Ledger
from tests.integration.ledger_sdk.anvil import anvil_node, deploy_contracts, fund, robot_ledger


@dataclass
class Deployment:
    url: str
    rpc: JsonRpcClient
    addresses: ContractAddresses
    admin: Ledger


@pytest.fixture(scope="module")
def deployment(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Deployment]:
    log = Path(tmp_path_factory.mktemp("anvil")) / "anvil.log"
    with anvil_node(log) as url, JsonRpcClient(url) as rpc:
        admin = fund(rpc, Identity.generate())
        addresses = deploy_contracts(rpc, admin)
        with robot_ledger(url, addresses, admin) as admin_ledger:
            yield Deployment(url, rpc, addresses, admin_ledger)


LedgerFactory = Callable[..., Ledger]


@pytest.fixture
def new_robot(deployment: Deployment) -> Iterator[LedgerFactory]:
    """A funded, fresh identity's Ledger (``funded=False`` for one without ether)."""
    opened: list[Ledger] = []

    def make(*, funded: bool = True) -> Ledger:
        identity = Identity.generate()
        if funded:
            fund(deployment.rpc, identity)
        ledger = robot_ledger(deployment.url, deployment.addresses, identity)
        opened.append(ledger)
        return ledger

    yield make
    for ledger in opened:
        ledger.close()
