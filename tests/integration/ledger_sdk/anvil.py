"""A real Ethereum node (anvil, pinned in contracts/package.json) for the SDK's ledger tests.

anvil speaks the same JSON-RPC as the ledger service's ``/rpc`` and as production nodes, and it
is independent of our service, so these tests pin down the SDK against a node we did not write.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest

from robocloud.identity import Identity
from robocloud.ledger import ContractAbi, ContractAddresses, JsonRpcClient, Ledger, Transactor
from tests.procs import free_port

REPO = Path(__file__).resolve().parents[3]
CONTRACTS = REPO / "contracts"
CHAIN_ID = 1337
ONE_ETHER = 10**18


def anvil_binary() -> Path | None:
    found = sorted(CONTRACTS.glob("node_modules/@foundry-rs/anvil-*/bin/anvil"))
    return found[0] if found else None


def require_anvil() -> Path:
    """anvil, or a skip; in CI (``CI`` set) its absence is a failure, never a silent skip."""
    binary = anvil_binary()
    if binary is None or shutil.which("node") is None:
        if os.environ.get("CI"):
            pytest.fail("anvil missing: run `npm ci --prefix contracts` before the tests")
        pytest.skip("anvil missing (npm ci --prefix contracts)")
    return binary


@contextmanager
def anvil_node(log_path: Path) -> Iterator[str]:
    """Run anvil on a free loopback port; yield its RPC URL; always stop it."""
    port = free_port()
    command = [str(require_anvil()), "--host", "127.0.0.1", "--port", str(port)]
    command += ["--chain-id", str(CHAIN_ID), "--accounts", "1"]
    url = f"http://127.0.0.1:{port}"
    with log_path.open("wb") as log:
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
        try:
            wait_ready(url, process, log_path)
            yield url
        finally:
            process.terminate()
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def wait_ready(url: str, process: subprocess.Popen[bytes], log_path: Path) -> None:
    deadline = time.monotonic() + 30
    payload = {"jsonrpc": "2.0", "id": 1, "method": "eth_chainId", "params": []}
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"anvil exited at start:\n{log_path.read_text()}")
        try:
            if httpx.post(url, json=payload, timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            time.sleep(0.05)
    raise RuntimeError(f"anvil not ready after 30 s:\n{log_path.read_text()}")


def fund(rpc: JsonRpcClient, identity: Identity, wei: int = ONE_ETHER) -> Identity:
    """Give ``identity`` ether with anvil's own cheat method (what a faucet would do)."""
    rpc.request("anvil_setBalance", [identity.address, hex(wei)])
    return identity


def artifact(name: str) -> dict[str, Any]:
    loaded: dict[str, Any] = json.loads((CONTRACTS / "build" / f"{name}.json").read_text())
    return loaded


def deploy_contracts(rpc: JsonRpcClient, admin: Identity) -> ContractAddresses:
    """Deploy Registry and AnchorLog from the committed artifacts, as the ledger does."""
    transactor = Transactor(rpc, admin)
    registry = transactor.deploy(ContractAbi.load("Registry"), artifact("Registry")["bytecode"])
    assert registry.contract_address is not None
    anchor_log = transactor.deploy(
        ContractAbi.load("AnchorLog"), artifact("AnchorLog")["bytecode"], registry.contract_address
    )
    assert anchor_log.contract_address is not None
    return ContractAddresses(registry.contract_address, anchor_log.contract_address)


def robot_ledger(url: str, addresses: ContractAddresses, identity: Identity | None) -> Ledger:
    return Ledger(JsonRpcClient(url), addresses, identity, receipt_timeout_s=10)
