"""The SDK against two nodes: anvil (a node we did not write) and the ledger service's ``/rpc``.

Every test in this package runs on both, once per module each; fresh robots per test.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from robocloud.client import ServiceClient
from robocloud.identity import Identity
from robocloud.ledger import ContractAddresses, JsonRpcClient, Ledger
from tests.integration.robocloud.ledger.nodes import (
    deploy_contracts,
    ethereum_node,
    fund,
    robot_ledger,
)
from tests.integration.services.ledger.conftest import admin_of, start_ledger


@dataclass
class Deployment:
    url: str
    rpc: JsonRpcClient
    addresses: ContractAddresses
    admin: Ledger
    fund: Callable[[Identity], object]


@contextmanager
def on_anvil(tmp: Path) -> Iterator[Deployment]:
    with ethereum_node(tmp / "anvil.log") as url, JsonRpcClient(url) as rpc:
        admin = fund(rpc, Identity.generate())
        addresses = deploy_contracts(rpc, admin)
        with robot_ledger(url, addresses, admin) as admin_ledger:
            yield Deployment(url, rpc, addresses, admin_ledger, lambda i: fund(rpc, i))


def faucet(service_url: str, identity: Identity) -> object:
    with ServiceClient(service_url, identity) as client:
        return client.post_json("/v1/faucet", {"address": identity.address})


@contextmanager
def on_service(tmp: Path) -> Iterator[Deployment]:
    process = start_ledger(tmp / "data")
    try:
        with Ledger.connect(process.url, admin_of(process)) as connected:
            url = f"{process.url}/rpc"
            addresses = connected.addresses
        with JsonRpcClient(url) as rpc, robot_ledger(url, addresses, admin_of(process)) as admin:
            yield Deployment(url, rpc, addresses, admin, lambda i: faucet(process.url, i))
    finally:
        process.stop()


@pytest.fixture(scope="module", params=["anvil", "service"])
def deployment(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Deployment]:
    start = on_anvil if request.param == "anvil" else on_service
    with start(Path(tmp_path_factory.mktemp(request.param))) as deployed:
        yield deployed


LedgerFactory = Callable[..., Ledger]


@pytest.fixture
def new_robot(deployment: Deployment) -> Iterator[LedgerFactory]:
    """A funded, fresh identity's Ledger (``funded=False`` for one without ether)."""
    opened: list[Ledger] = []

    def make(*, funded: bool = True) -> Ledger:
        identity = Identity.generate()
        if funded:
            deployment.fund(identity)
        ledger = robot_ledger(deployment.url, deployment.addresses, identity)
        opened.append(ledger)
        return ledger

    yield make
    for ledger in opened:
        ledger.close()
