"""ledger in Compose: a robot registered through the published port stays registered across a
restart, and the other services let it write because they ask the ledger by service name."""

from __future__ import annotations

import httpx
import pytest

from robocloud.identity import Identity
from robocloud.ledger import Ledger
from tests.compose.deployment import Deployment

pytestmark = pytest.mark.compose

METADATA = bytes.fromhex("01551220") + bytes(range(32))


def test_register_restart_still_registered(deployment: Deployment) -> None:
    robot = Identity.generate()
    url = deployment.urls["ledger"]
    with Ledger.connect(url, robot, receipt_timeout_s=30) as ledger:
        ledger.faucet()
        receipt = ledger.register(METADATA)
    head = httpx.get(f"{url}/v1/blocks/latest", timeout=10).json()

    deployment.restart(["ledger"])
    assert httpx.get(f"{url}/v1/blocks/latest", timeout=10).json()["hash"] == head["hash"]
    record = httpx.get(f"{url}/v1/robots/{robot.address}", timeout=10).json()
    assert (record["active"], record["registered_block"]) == (True, receipt.block_number)
    with Ledger.connect(url, robot) as ledger:
        assert ledger.robot(robot.address).is_active

    with deployment.client("storage", robot) as storage:
        assert storage.post_json("/v1/whoami")["address"] == robot.address
