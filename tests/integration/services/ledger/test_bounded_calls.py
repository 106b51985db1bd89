"""An infinite loop through eth_call: capped, cut off in time, and nobody else waits for it."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from web3 import HTTPProvider, Web3

from robocloud.identity import Identity
from tests.integration.services.ledger.conftest import faucet, rpc, start_ledger
from tests.procs import ServiceProcess

TIMEOUT_S = 3
LOOP_RUNTIME = "5b600056"  # JUMPDEST PUSH1 0 JUMP: forever
DEPLOY_LOOP = "635b6000566000526004601cf3"  # return those 4 bytes as the contract's code


@pytest.fixture(scope="module")
def ledger(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    process = start_ledger(
        tmp_path_factory.mktemp("bounded") / "data",
        {"ROBOCLOUD_LEDGER_RPC_EVM_TIMEOUT_S": str(TIMEOUT_S)},
    )
    try:
        yield process
    finally:
        process.stop()


@pytest.fixture(scope="module")
def loop_address(ledger: ServiceProcess) -> str:
    return deploy_loop(ledger.url)


def deploy_loop(url: str) -> str:
    """A contract whose code loops forever, deployed by a faucet-funded robot."""
    robot = Identity.generate()
    assert faucet(url, robot).status_code == 200
    w3 = Web3(HTTPProvider(f"{url}/rpc"))
    signed = robot.account.sign_transaction(
        {
            "chainId": 1337,
            "nonce": 0,
            "gas": 100_000,
            "maxFeePerGas": 10**10,
            "maxPriorityFeePerGas": 10**9,
            "data": "0x" + DEPLOY_LOOP,
        }
    )
    receipt = w3.eth.wait_for_transaction_receipt(
        w3.eth.send_raw_transaction(signed.raw_transaction), timeout=30
    )
    assert w3.eth.get_code(receipt["contractAddress"]).hex() == LOOP_RUNTIME
    return str(receipt["contractAddress"])


def call_loop(url: str, address: str, **extra: Any) -> dict[str, Any]:
    return rpc(url, "eth_call", [{"to": address, **extra}, "latest"])


@pytest.mark.parametrize(
    "extra", [{}, {"gas": hex(2**63)}, {"gas": hex(2**256 - 1)}], ids=["default", "2^63", "max"]
)
def test_a_call_that_never_ends_is_aborted_like_geth(
    ledger: ServiceProcess, loop_address: str, extra: dict[str, Any]
) -> None:
    answer = call_loop(ledger.url, loop_address, **extra)
    assert answer["error"] == {
        "code": -32000,
        "message": f"execution aborted (timeout = {TIMEOUT_S}s)",
    }


def test_estimate_gas_of_the_loop_is_aborted_too(ledger: ServiceProcess, loop_address: str) -> None:
    answer = rpc(ledger.url, "eth_estimateGas", [{"to": loop_address}])
    assert answer["error"]["message"] == f"execution aborted (timeout = {TIMEOUT_S}s)"


def test_reads_transactions_and_readiness_go_on_while_the_loop_runs(
    ledger: ServiceProcess, loop_address: str
) -> None:
    finished = threading.Event()

    def run_loop() -> None:
        call_loop(ledger.url, loop_address, gas=hex(2**63))
        finished.set()

    worker = threading.Thread(target=run_loop)
    worker.start()
    try:
        robot = Identity.generate()
        assert faucet(ledger.url, robot).status_code == 200
        number = rpc(ledger.url, "eth_blockNumber", [])["result"]
        ready = httpx.get(f"{ledger.url}/readyz", timeout=30)
        balance = rpc(ledger.url, "eth_getBalance", [robot.address, "latest"])["result"]
        assert not finished.is_set(), "the loop should still be running"
    finally:
        worker.join()
    assert int(number, 16) >= 2
    assert ready.json()["status"] == "ready"
    assert int(balance, 16) > 0


def test_sigterm_stops_the_service_while_a_call_runs(tmp_path: Path) -> None:
    process = start_ledger(tmp_path / "data", {"ROBOCLOUD_LEDGER_RPC_EVM_TIMEOUT_S": "120"})
    try:
        address = deploy_loop(process.url)
        outcome: list[str] = []

        def run_loop() -> None:
            payload = {"jsonrpc": "2.0", "id": 1, "method": "eth_call", "params": [{"to": address}]}
            try:
                response = httpx.post(f"{process.url}/rpc", json=payload, timeout=60)
                outcome.append(str(response.status_code))
            except httpx.HTTPError as exc:
                outcome.append(type(exc).__name__)

        worker = threading.Thread(target=run_loop)
        worker.start()
        worker.join(timeout=1)  # let the call reach the EVM; it runs for minutes if let be
        assert process.process is not None
        process.process.send_signal(signal.SIGTERM)
        assert process.process.wait(timeout=30) is not None
        worker.join()
        assert outcome in (["500"], ["RemoteProtocolError"]), outcome
    finally:
        process.stop()
