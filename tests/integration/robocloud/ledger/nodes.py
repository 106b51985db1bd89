"""Real Ethereum nodes for the ledger tests: anvil and hardhat@2, pinned in contracts/.

Both speak the same JSON-RPC as the ledger service's ``/rpc`` and as production nodes, and both
are independent of our service, so these tests pin down the SDK and external-node mode against
nodes we did not write. anvil is the default (it starts in a fraction of a second); hardhat is
the node the ledger issue names for external-node mode.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest

from robocloud.identity import Identity
from robocloud.ledger import ContractAbi, ContractAddresses, JsonRpcClient, Ledger, Transactor
from tests.procs import free_port

REPO = Path(__file__).resolve().parents[4]
CONTRACTS = REPO / "contracts"
CHAIN_ID = 1337
ONE_ETHER = 10**18


NODES = ("anvil", "hardhat")


def node_binary(kind: str) -> Path | None:
    """Where ``npm ci --prefix contracts`` put the node's executable, if it did."""
    if kind == "anvil":
        found = sorted(CONTRACTS.glob("node_modules/@foundry-rs/anvil-*/bin/anvil"))
        return found[0] if found else None
    if kind == "hardhat":
        binary = CONTRACTS / "node_modules" / ".bin" / "hardhat"
        return binary if binary.exists() else None
    raise ValueError(f"unknown node {kind!r}")


def node_command(kind: str, port: int, extra: Sequence[str] = ()) -> list[str]:
    """How to start ``kind`` on ``port``; in CI a missing node fails, never silently skips."""
    binary = node_binary(kind)
    if binary is None or shutil.which("node") is None:
        if os.environ.get("CI"):
            pytest.fail(f"{kind} missing: run `npm ci --prefix contracts` before the tests")
        pytest.skip(f"{kind} missing (npm ci --prefix contracts)")
    if kind == "hardhat":
        return [str(binary), "node", "--hostname", "127.0.0.1", "--port", str(port), *extra]
    address = ["--host", "127.0.0.1", "--port", str(port)]
    return [str(binary), *address, "--chain-id", str(CHAIN_ID), "--accounts", "1", *extra]


@contextmanager
def ethereum_node(log_path: Path, kind: str = "anvil", extra: Sequence[str] = ()) -> Iterator[str]:
    """Run a node of ``kind`` (with ``extra`` arguments) on a free loopback port; yield its RPC
    URL; always stop it."""
    port = free_port()
    command = node_command(kind, port, extra)
    url = f"http://127.0.0.1:{port}"
    with log_path.open("wb") as log:
        process = subprocess.Popen(
            command, cwd=CONTRACTS, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
        )
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
            raise RuntimeError(f"node exited at start:\n{log_path.read_text()}")
        try:
            if httpx.post(url, json=payload, timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            time.sleep(0.05)
    raise RuntimeError(f"node not ready after 30 s:\n{log_path.read_text()}")


def fund(rpc: JsonRpcClient, identity: Identity, wei: int = ONE_ETHER) -> Identity:
    """Give ``identity`` ether with the nodes' cheat method (what a faucet would do)."""
    rpc.request("hardhat_setBalance", [identity.address, hex(wei)])
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
