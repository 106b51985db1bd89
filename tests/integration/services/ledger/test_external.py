"""External-node mode against real nodes (hardhat@2 and anvil): deploy or attach, forward,
index by polling."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import httpx
import pytest

from robocloud.identity import Identity
from robocloud.ledger import JsonRpcClient, Ledger, RegistrationMode
from tests.integration.robocloud.ledger.nodes import NODES, deploy_contracts, ethereum_node, fund
from tests.integration.services.ledger.conftest import (
    METADATA,
    PASSPHRASE,
    faucet,
    rpc,
    start_ledger,
)
from tests.procs import ServiceProcess

T = TypeVar("T")


@pytest.fixture(params=NODES)
def node(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[str]:
    with ethereum_node(tmp_path / "node.log", request.param) as url:
        yield url


def external(data_dir: Path, node: str, env: dict[str, str] | None = None) -> ServiceProcess:
    settings = {"ROBOCLOUD_LEDGER_RPC_URL": node, "ROBOCLOUD_LEDGER_POLL_INTERVAL_S": "0.1"}
    return start_ledger(data_dir, {**settings, **(env or {})})


def eventually(read: Callable[[], T | None], what: str) -> T:
    """What ``read`` returns once it is not None: the index follows the node by polling."""
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        found = read()
        if found is not None:
            return found
        time.sleep(0.1)
    raise AssertionError(f"{what} never appeared in the index")


def wait_for_robot(url: str, address: str) -> dict[str, Any]:
    def read() -> dict[str, Any] | None:
        response = httpx.get(f"{url}/v1/robots/{address}")
        return response.json() if response.status_code == 200 else None

    return eventually(read, f"robot {address}")


def wait_for_advertisements(url: str, advertiser: str) -> list[dict[str, Any]]:
    def read() -> list[dict[str, Any]] | None:
        rows = httpx.get(f"{url}/v1/advertisements", params={"advertiser": advertiser})
        return rows.json()["advertisements"] or None

    return eventually(read, f"an advertisement by {advertiser}")


def test_deploys_with_the_operator_key_and_indexes_by_polling(tmp_path: Path, node: str) -> None:
    data_dir = tmp_path / "data"
    admin = Identity.generate()
    admin.save(data_dir / "keys" / "admin.json", PASSPHRASE, scrypt_n=2**14)
    with JsonRpcClient(node) as chain:
        fund(chain, admin)
        process = external(data_dir, node)
        try:
            robot = fund(chain, Identity.generate())
            with Ledger.connect(process.url, robot, receipt_timeout_s=10) as ledger:
                assert ledger.admin() == admin.address
                ledger.register(METADATA)
                advertised = ledger.advertise(b"\x01\x55\x12\x20" + bytes(32))
                assert ledger.advertisements(advertiser=robot.address) == [advertised]
            assert wait_for_robot(process.url, robot.address)["active"] is True
            rows = wait_for_advertisements(process.url, robot.address)
            assert [row["tx"] for row in rows] == [advertised.tx_hash]
            contracts = httpx.get(f"{process.url}/v1/contracts").json()

            refused = faucet(process.url, Identity.generate())
            assert refused.status_code == 404
            assert refused.json()["error"]["code"] == "faucet_unavailable"
            cheat = rpc(process.url, "hardhat_setBalance", [robot.address, "0x1"])
            assert cheat["error"]["code"] == -32601

            process.restart()
            assert httpx.get(f"{process.url}/v1/contracts").json() == contracts
            assert wait_for_robot(process.url, robot.address)["active"] is True
        finally:
            process.stop()


def test_attaches_to_configured_addresses(tmp_path: Path, node: str) -> None:
    with JsonRpcClient(node) as chain:
        addresses = deploy_contracts(chain, fund(chain, Identity.generate()))
        robot = fund(chain, Identity.generate())
        with Ledger(JsonRpcClient(node), addresses, robot) as direct:
            direct.register(METADATA)
        env = {
            "ROBOCLOUD_LEDGER_REGISTRY_ADDRESS": addresses.registry,
            "ROBOCLOUD_LEDGER_ANCHOR_LOG_ADDRESS": addresses.anchor_log,
            "ROBOCLOUD_LEDGER_LOG_PAGE_BLOCKS": "2",
        }
        process = external(tmp_path / "data", node, env)
        try:
            contracts = httpx.get(f"{process.url}/v1/contracts").json()["contracts"]
            assert contracts["Registry"]["address"] == addresses.registry
            assert wait_for_robot(process.url, robot.address)["registered_block"] > 0
            assert not (tmp_path / "data" / "keys").exists()
        finally:
            process.stop()


def mode_of(url: str) -> RegistrationMode:
    with Ledger.connect(url) as reader:
        return reader.registration_mode()


def test_the_operator_key_applies_the_registration_mode_at_every_start(
    tmp_path: Path, node: str
) -> None:
    data_dir = tmp_path / "data"
    admin = Identity.generate()
    admin.save(data_dir / "keys" / "admin.json", PASSPHRASE, scrypt_n=2**14)
    with JsonRpcClient(node) as chain:
        fund(chain, admin)
        process = external(data_dir, node, {"ROBOCLOUD_LEDGER_REGISTRATION_MODE": "approved"})
        try:
            assert mode_of(process.url) is RegistrationMode.APPROVED
            robot = fund(chain, Identity.generate())
            with Ledger.connect(process.url, robot, receipt_timeout_s=10) as ledger:
                ledger.register(METADATA)
            record = wait_for_robot(process.url, robot.address)
            assert (record["status"], record["active"]) == ("pending", False)
            listed = httpx.get(f"{process.url}/v1/registrations").json()["pending"]
            assert [entry["address"] for entry in listed] == [robot.address]

            process.env["ROBOCLOUD_LEDGER_REGISTRATION_MODE"] = "open"
            process.restart()
            assert mode_of(process.url) is RegistrationMode.OPEN
            assert wait_for_robot(process.url, robot.address)["status"] == "pending"
        finally:
            process.stop()


def test_an_attached_ledger_refuses_to_misstate_the_mode(tmp_path: Path, node: str) -> None:
    with JsonRpcClient(node) as chain:
        owner = fund(chain, Identity.generate())
        addresses = deploy_contracts(chain, owner)
        with Ledger(JsonRpcClient(node), addresses, owner) as registry_admin:
            registry_admin.set_registration_mode(RegistrationMode.APPROVED)
        env = {
            "ROBOCLOUD_LEDGER_REGISTRY_ADDRESS": addresses.registry,
            "ROBOCLOUD_LEDGER_ANCHOR_LOG_ADDRESS": addresses.anchor_log,
        }
        with pytest.raises(RuntimeError, match="exited at start") as exited:
            external(tmp_path / "open", node, env | {"ROBOCLOUD_LEDGER_REGISTRATION_MODE": "open"})
        assert f"the Registry at {addresses.registry} is in the approved registration mode" in str(
            exited.value
        )
        assert not (tmp_path / "open" / "keys").exists()

        process = external(
            tmp_path / "approved", node, env | {"ROBOCLOUD_LEDGER_REGISTRATION_MODE": "approved"}
        )
        try:
            assert mode_of(process.url) is RegistrationMode.APPROVED
        finally:
            process.stop()
