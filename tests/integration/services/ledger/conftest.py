"""A ledger service process per module, and helpers to drive it as robots and as its admin."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

from robocloud.identity import Identity
from robocloud.ledger import Ledger
from robocloud.signing import sign_request
from tests.procs import ServiceProcess, audience_of

PASSPHRASE = "integration-tests-only"
LEDGER_ENV = {
    "ROBOCLOUD_LEDGER_ADMIN_PASSPHRASE": PASSPHRASE,
    "ROBOCLOUD_LEDGER_FAUCET_PER_MINUTE": "1000",
}
METADATA = bytes.fromhex("01551220") + bytes(range(32))


def admin_of(process: ServiceProcess) -> Identity:
    """The operator's admin key, read the way an operator would: keystore + passphrase."""
    return Identity.load(process.data_dir / "keys" / "admin.json", PASSPHRASE)


def rpc(url: str, method: str, params: list[Any]) -> dict[str, Any]:
    """One raw JSON-RPC exchange: the whole response document, errors included."""
    payload = {"jsonrpc": "2.0", "id": 1, "method": method, "params": params}
    response = httpx.post(f"{url}/rpc", json=payload, timeout=30)
    assert response.status_code == 200, response.text
    document: dict[str, Any] = response.json()
    return document


def head(url: str) -> dict[str, Any]:
    block: dict[str, Any] = httpx.get(f"{url}/v1/blocks/latest").json()
    return block


@dataclass
class Service:
    process: ServiceProcess
    admin: Ledger

    @property
    def url(self) -> str:
        return self.process.url


def start_ledger(data_dir: Path, env: dict[str, str] | None = None) -> ServiceProcess:
    return ServiceProcess("ledger", data_dir, {**LEDGER_ENV, **(env or {})}).start()


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    process = start_ledger(tmp_path_factory.mktemp("ledger") / "data")
    try:
        with Ledger.connect(process.url, admin_of(process), receipt_timeout_s=10) as admin:
            yield Service(process, admin)
    finally:
        process.stop()


RobotFactory = Callable[..., Ledger]


@pytest.fixture
def robot(service: Service) -> Iterator[RobotFactory]:
    """A fresh identity's Ledger; funded by the faucet and registered unless told otherwise."""
    opened: list[Ledger] = []

    def make(*, funded: bool = True, registered: bool = True) -> Ledger:
        ledger = Ledger.connect(service.url, Identity.generate(), receipt_timeout_s=10)
        opened.append(ledger)
        if funded:
            ledger.faucet()
        if registered:
            ledger.register(METADATA)
        return ledger

    yield make
    for ledger in opened:
        ledger.close()


def signed_post(url: str, path: str, identity: Identity, body: Any) -> httpx.Response:
    """A signed JSON POST, answered whatever its status (the SDK would raise on errors)."""
    content = json.dumps(body).encode()
    headers = sign_request(
        identity.account,
        audience_of(url),
        "POST",
        path,
        content_sha256=hashlib.sha256(content).hexdigest(),
    )
    headers["Content-Type"] = "application/json"
    return httpx.post(f"{url}{path}", content=content, headers=headers, timeout=30)


def faucet(url: str, identity: Identity, address: str | None = None) -> httpx.Response:
    return signed_post(url, "/v1/faucet", identity, {"address": address or identity.address})
