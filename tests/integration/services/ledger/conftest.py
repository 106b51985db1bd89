"""A ledger service process per module, and helpers to drive it as robots and as its admin."""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

from robocloud.identity import Identity
from robocloud.ledger import JsonRpcClient, Ledger
from robocloud.signing import sign_request
from tests.integration.robocloud.ledger.nodes import ethereum_node, fund
from tests.procs import ServiceProcess, audience_of
from tests.rawtx import RawTx

PASSPHRASE = "integration-tests-only"
LEDGER_ENV = {
    "ROBOCLOUD_LEDGER_ADMIN_PASSPHRASE": PASSPHRASE,
    "ROBOCLOUD_LEDGER_FAUCET_PER_MINUTE": "1000",
}


def ledger_fronting(
    service_factory: Callable[..., ServiceProcess],
    anvil_url: str,
    anvil: JsonRpcClient,
    data_dir: Path,
    storage_url: str | None = None,
) -> ServiceProcess:
    """A ledger service in external-node mode in front of the anvil at ``anvil_url``, its
    admin key funded there, polling the node every 0.2 s (``storage_url``: the storage node
    it grants the storage role to)."""
    admin = Identity.generate()
    admin.save(data_dir / "keys" / "admin.json", PASSPHRASE, scrypt_n=2**14)
    fund(anvil, admin)
    env = {
        **LEDGER_ENV,
        "ROBOCLOUD_LEDGER_RPC_URL": anvil_url,
        "ROBOCLOUD_LEDGER_POLL_INTERVAL_S": "0.2",
    }
    if storage_url is not None:
        env["ROBOCLOUD_STORAGE_URL"] = storage_url
    return service_factory("ledger", env, data_dir=data_dir)


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


def call(url: str, method: str, params: Any) -> dict[str, Any]:
    """One JSON-RPC exchange with a node's endpoint ``url`` (the ledger's ends in /rpc)."""
    payload = {"jsonrpc": "2.0", "id": 1, "method": method, "params": params}
    answer: dict[str, Any] = httpx.post(url, json=payload, timeout=60).json()
    return answer


def result(url: str, method: str, params: Any) -> Any:
    answer = call(url, method, params)
    assert "result" in answer, answer
    return answer["result"]


def mined(url: str, tx_hash: str, timeout_s: float = 10.0) -> dict[str, Any]:
    """The receipt of ``tx_hash``, waited for: anvil answers eth_sendRawTransaction before its
    miner task has sealed the block, so a receipt asked for at once can still be null there."""
    deadline = time.monotonic() + timeout_s
    while (receipt := result(url, "eth_getTransactionReceipt", [tx_hash])) is None:
        assert time.monotonic() < deadline, f"{tx_hash} not mined on {url} in {timeout_s} s"
        time.sleep(0.02)
    assert isinstance(receipt, dict)
    return receipt


@dataclass
class Pair:
    """The ledger's /rpc and a fresh anvil: the same request to both, answers compared."""

    ledger: str
    anvil: str

    @property
    def service_url(self) -> str:
        return self.ledger.removesuffix("/rpc")

    @property
    def urls(self) -> tuple[str, str]:
        return self.ledger, self.anvil

    def funded(self) -> Identity:
        """A fresh key with ether on both chains."""
        identity = Identity.generate()
        assert faucet(self.service_url, identity).status_code == 200
        with JsonRpcClient(self.anvil) as anvil:
            fund(anvil, identity)
        return identity

    def deploy(self, identity: Identity, init_code: bytes) -> tuple[str, str]:
        """Deploy ``init_code`` from ``identity`` on both; the two contract addresses."""
        addresses = []
        for url in self.urls:
            nonce = int(result(url, "eth_getTransactionCount", [identity.address, "latest"]), 16)
            tx = RawTx(nonce=nonce, to=b"", data=init_code, gas=1_000_000, max_fee=10**11)
            tx_hash = result(url, "eth_sendRawTransaction", [tx.sign(bytes(identity.account.key))])
            receipt = mined(url, tx_hash)
            assert receipt["status"] == "0x1", receipt
            addresses.append(receipt["contractAddress"])
        return addresses[0], addresses[1]


@pytest.fixture(scope="module")
def pair(service: Service, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Pair]:
    with ethereum_node(tmp_path_factory.mktemp("anvil") / "anvil.log") as anvil:
        yield Pair(f"{service.url}/rpc", anvil)


def deploying(runtime: bytes) -> bytes:
    """Init code that returns ``runtime`` (at most 255 bytes) as the contract's code."""
    assert len(runtime) < 256
    return bytes.fromhex(f"60{len(runtime):02x}80600b6000396000f3") + runtime
