"""An infinite loop through eth_call: capped, cut off in time, and nobody else waits for it."""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from py_ecc import optimized_bn128 as bn254
from web3 import HTTPProvider, Web3

from robocloud.identity import Identity
from robocloud.ledger import JsonRpcClient
from tests.flood import flooding
from tests.integration.robocloud.ledger.nodes import ethereum_node, fund
from tests.integration.services.ledger.conftest import PASSPHRASE, faucet, rpc, start_ledger
from tests.procs import ServiceProcess
from tests.unit.services.ledger.test_chain import DEPLOY_LOOP, LOOP_RUNTIME

TIMEOUT_S = 3


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
    return deploy_code(f"{url}/rpc", robot, DEPLOY_LOOP, LOOP_RUNTIME)


def deploy_code(rpc_url: str, robot: Identity, init_code: str, runtime: str) -> str:
    """Deploy raw ``init_code`` from a funded ``robot``; the contract's address."""
    w3 = Web3(HTTPProvider(rpc_url))
    signed = robot.account.sign_transaction(
        {
            "chainId": 1337,
            "nonce": w3.eth.get_transaction_count(robot.address),
            "gas": 200_000,
            "maxFeePerGas": 10**10,
            "maxPriorityFeePerGas": 10**9,
            "data": "0x" + init_code,
        }
    )
    receipt = w3.eth.wait_for_transaction_receipt(
        w3.eth.send_raw_transaction(signed.raw_transaction), timeout=30
    )
    assert w3.eth.get_code(receipt["contractAddress"]).hex() == runtime
    return str(receipt["contractAddress"])


def call_loop(url: str, address: str, **extra: Any) -> dict[str, Any]:
    return rpc(url, "eth_call", [{"to": address, **extra}, "latest"])


@pytest.mark.parametrize(
    "extra", [{}, {"gas": hex(2**63)}, {"gas": hex(2**64 - 1)}], ids=["default", "2^63", "max"]
)
def test_a_call_that_never_ends_is_aborted_like_geth(
    ledger: ServiceProcess, loop_address: str, extra: dict[str, Any]
) -> None:
    answer = call_loop(ledger.url, loop_address, **extra)
    assert answer["error"] == {
        "code": -32000,
        "message": f"execution aborted (timeout = {TIMEOUT_S}s)",
    }


def bn254_pairs(count: int) -> str:
    """``count`` pairs (G1, G2), then as many (-G1, G2): pairings whose product is one."""
    g1 = bn254.normalize(bn254.G1)
    minus_g1 = bn254.normalize(bn254.neg(bn254.G1))
    x, y = bn254.normalize(bn254.G2)
    g2 = b"".join(n.to_bytes(32, "big") for n in (*reversed(x.coeffs), *reversed(y.coeffs)))

    def g1_bytes(point: Any) -> bytes:
        return b"".join(int(n).to_bytes(32, "big") for n in point)

    pairs = [g1_bytes(g1) + g2] * count + [g1_bytes(minus_g1) + g2] * count
    return "0x" + b"".join(pairs).hex()


def test_a_pairing_that_would_outlast_the_deadline_is_aborted_before_it_starts(
    ledger: ServiceProcess,
) -> None:
    """py-evm pairs in pure Python and a precompile cannot be stopped half-way: 40 pairings
    ran 7 s past a 5 s timeout, and 2^24 gas of them would hold a worker for minutes. 10
    pairings take about 3.6 s: within a transaction's budget for them, past the call's 3 s."""
    pairing = "0x" + "00" * 19 + "08"
    one = "0x" + "00" * 31 + "01"
    assert rpc(ledger.url, "eth_call", [{"to": pairing, "data": bn254_pairs(1)}, "latest"]) == {
        "jsonrpc": "2.0",
        "id": 1,
        "result": one,
    }
    answer = rpc(ledger.url, "eth_call", [{"to": pairing, "data": bn254_pairs(5)}, "latest"])
    assert answer["error"] == {
        "code": -32000,
        "message": f"execution aborted (timeout = {TIMEOUT_S}s)",
    }


def test_a_call_with_more_gas_than_64_bits_is_invalid(
    ledger: ServiceProcess, loop_address: str
) -> None:
    """A call's gas is a uint64 in geth and anvil (-32602); it used to be run, capped."""
    answer = call_loop(ledger.url, loop_address, gas=hex(2**256 - 1))
    assert answer["error"]["code"] == -32602


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


RECIPIENT = Web3.to_checksum_address("0x" + "22" * 20)


def transfer(rpc_url: str, robot: Identity, nonce: int) -> Any:
    """Five wei from ``robot`` to ``RECIPIENT`` through ``rpc_url``; the receipt."""
    w3 = Web3(HTTPProvider(rpc_url, request_kwargs={"timeout": 15}))
    signed = robot.account.sign_transaction(
        {
            "chainId": 1337,
            "nonce": nonce,
            "gas": 21_000,
            "maxFeePerGas": 10**10,
            "maxPriorityFeePerGas": 10**9,
            "to": RECIPIENT,
            "value": 5,
        }
    )
    return w3.eth.wait_for_transaction_receipt(
        w3.eth.send_raw_transaction(signed.raw_transaction), timeout=15
    )


FLOODERS = 48
"""More than the service's 40 worker threads: before calls took turns in slots, a flood this
size left a transaction and a balance read waiting past 30 s."""


def test_a_flood_of_looping_calls_starves_no_transaction_or_read(
    ledger: ServiceProcess, loop_address: str
) -> None:
    payload = {"jsonrpc": "2.0", "id": 1, "method": "eth_call", "params": [{"to": loop_address}]}

    def looping_call(client: httpx.Client) -> dict[str, Any]:
        answer: dict[str, Any] = client.post(f"{ledger.url}/rpc", json=payload).json()
        return answer

    with flooding(looping_call, FLOODERS) as flood:
        robot = Identity.generate()
        funded = faucet(ledger.url, robot)
        receipt = transfer(f"{ledger.url}/rpc", robot, nonce=0)
        w3 = Web3(HTTPProvider(f"{ledger.url}/rpc", request_kwargs={"timeout": 15}))
        recipient_balance = w3.eth.get_balance(RECIPIENT)
        ready = httpx.get(f"{ledger.url}/readyz", timeout=15)
        # The flood's address holds one call slot, as its share; the other is this client's.
        call = honest_call(f"{ledger.url}/rpc")
        still_flooding = flood.running()
    assert call == {"jsonrpc": "2.0", "id": 1, "result": "0x"}
    assert funded.status_code == 200
    assert receipt["status"] == 1
    assert recipient_balance >= 5
    assert ready.json()["status"] == "ready"
    assert still_flooding
    aborted = {"code": -32000, "message": f"execution aborted (timeout = {TIMEOUT_S}s)"}
    over_share = share_refusal(2)
    errors = [answer["error"] for answer in flood.answers]
    assert aborted in errors
    assert over_share in errors
    assert all(error in (aborted, over_share, slots_refusal(2)) for error in errors), errors


def test_a_flood_of_looping_calls_relayed_to_a_node_starves_nothing(tmp_path: Path) -> None:
    """External-node mode relayed each call from a worker thread: a flood held all forty, a
    transfer behind it timed out after 15 s, ``/readyz`` answered 503 and the flooders waited
    past 120 s."""
    with (
        ethereum_node(tmp_path / "anvil.log", "anvil", ["--disable-block-gas-limit"]) as node,
        JsonRpcClient(node) as chain,
    ):
        admin = Identity.generate()
        admin.save(tmp_path / "data" / "keys" / "admin.json", PASSPHRASE, scrypt_n=2**14)
        fund(chain, admin)
        env = {
            "ROBOCLOUD_LEDGER_RPC_URL": node,
            "ROBOCLOUD_LEDGER_RPC_EVM_TIMEOUT_S": str(TIMEOUT_S),
            "ROBOCLOUD_LEDGER_RPC_MAX_CALLS": "1",
        }
        process = start_ledger(tmp_path / "data", env)
        try:
            loop = deploy_code(node, fund(chain, Identity.generate()), DEPLOY_LOOP, LOOP_RUNTIME)
            # a second or two of looping in anvil, which stops a call only when its gas is spent
            call = {"to": loop, "gas": hex(2 * 10**9)}
            payload = {"jsonrpc": "2.0", "id": 1, "method": "eth_call", "params": [call, "latest"]}

            def looping_call(client: httpx.Client) -> dict[str, Any]:
                answer: dict[str, Any] = client.post(f"{process.url}/rpc", json=payload).json()
                return answer

            robot = fund(chain, Identity.generate())
            with flooding(looping_call, FLOODERS) as flood:
                time.sleep(1)
                receipt = transfer(f"{process.url}/rpc", robot, nonce=0)
                ready = httpx.get(f"{process.url}/readyz", timeout=15)
                contracts = httpx.get(f"{process.url}/v1/contracts", timeout=15)
                # Next in line for the one call slot: the flood's other calls wait for its share.
                call = honest_call(f"{process.url}/rpc")
                still_flooding = flood.running()
        finally:
            process.stop()
    assert call == {"jsonrpc": "2.0", "id": 1, "result": "0x"}
    assert receipt["status"] == 1
    assert ready.json()["status"] == "ready"
    assert set(contracts.json()["contracts"]) == {"Registry", "AnchorLog"}
    assert still_flooding
    out_of_gas = {"code": -32603, "message": "EVM error OutOfGas"}
    timed_out = {"code": -32002, "message": "request timed out"}
    errors = [answer["error"] for answer in flood.answers]
    assert share_refusal(1) in errors
    expected = (out_of_gas, share_refusal(1), slots_refusal(1), timed_out)
    assert all(error in expected for error in errors), errors


def honest_call(rpc_url: str) -> dict[str, Any]:
    """An ``eth_call`` from the test's own address, another client than the flood's."""
    call = {"to": RECIPIENT, "data": "0x"}
    payload = {"jsonrpc": "2.0", "id": 1, "method": "eth_call", "params": [call, "latest"]}
    answer: dict[str, Any] = httpx.post(rpc_url, json=payload, timeout=15).json()
    return answer


def share_refusal(slots: int) -> dict[str, Any]:
    """What a flooder gets when its address already holds its share of the call slots."""
    return {
        "code": -32005,
        "message": f"limit exceeded: this client already holds {max(1, slots // 2)} of the "
        f"{slots} call slots, its share, and none came free in {TIMEOUT_S} s; retry later",
    }


def slots_refusal(slots: int) -> dict[str, Any]:
    """What a flooder gets when its share had room and every slot stayed busy."""
    return {
        "code": -32005,
        "message": f"limit exceeded: all {slots} call slots stayed busy for {TIMEOUT_S} s; "
        "retry later",
    }


def test_a_batch_of_looping_calls_starts_none_after_its_deadline_as_geth_does(
    ledger: ServiceProcess, loop_address: str
) -> None:
    """Calls one after another in a batch used to run ten times the EVM timeout."""
    call = {"to": loop_address}
    batch = [{"jsonrpc": "2.0", "id": n, "method": "eth_call", "params": [call]} for n in range(10)]
    answers = httpx.post(f"{ledger.url}/rpc", json=batch, timeout=60).json()
    aborted = {"code": -32000, "message": f"execution aborted (timeout = {TIMEOUT_S}s)"}
    timed_out = {"code": -32002, "message": "request timed out"}
    assert answers == [
        {"jsonrpc": "2.0", "id": 0, "error": aborted},
        *({"jsonrpc": "2.0", "id": n, "error": timed_out} for n in range(1, 10)),
    ]


def test_sigterm_stops_the_service_while_a_call_runs(tmp_path: Path) -> None:
    # Gas for hours of looping: with a block's worth, the loop runs out of gas within the
    # shutdown's grace period on a fast machine, and is answered before the service stops.
    env = {"ROBOCLOUD_LEDGER_RPC_EVM_TIMEOUT_S": "120", "ROBOCLOUD_LEDGER_RPC_GAS_CAP": str(10**12)}
    process = start_ledger(tmp_path / "data", env)
    try:
        address = deploy_loop(process.url)
        outcome: list[str] = []

        def run_loop() -> None:
            call = {"to": address, "gas": hex(10**12)}
            payload = {"jsonrpc": "2.0", "id": 1, "method": "eth_call", "params": [call]}
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


# Called with n, calls itself with n - 1 and returns what it got; at n = 0 returns 1. So it
# answers 1 exactly when n nested calls fit in the EVM's depth limit of 1024, else nothing.
RECURSE_RUNTIME = (
    "60003580156027576001900360005260206000602060006000305af1503d600060003e3d6000f3"
    "5b600160005260206000f3"
)
DEPLOY_RECURSE = "603280600b6000396000f3" + RECURSE_RUNTIME
DEEP_GAS = 10**13
"""With the 63/64 rule, 1,024 nested calls need more gas than a block holds."""


def call_recurse(rpc_url: str, address: str, depth: int) -> str:
    payload = {
        "jsonrpc": "2.0",
        "id": 1,
        "method": "eth_call",
        "params": [
            {"to": address, "data": "0x" + depth.to_bytes(32, "big").hex(), "gas": hex(DEEP_GAS)},
            "latest",
        ],
    }
    answer: str = httpx.post(rpc_url, json=payload, timeout=120).json()["result"]
    return answer


def test_calls_nest_to_the_evm_depth_limit_as_anvil_does(tmp_path: Path) -> None:
    """py-evm recurses in Python for every nested call: the ledger must give it the room."""
    ledger = start_ledger(
        tmp_path / "data",
        {
            "ROBOCLOUD_LEDGER_RPC_GAS_CAP": str(DEEP_GAS),
            "ROBOCLOUD_LEDGER_RPC_EVM_TIMEOUT_S": "120",
        },
    )
    try:
        robot = Identity.generate()
        assert faucet(ledger.url, robot).status_code == 200
        ours = deploy_code(f"{ledger.url}/rpc", robot, DEPLOY_RECURSE, RECURSE_RUNTIME)
        with (
            ethereum_node(tmp_path / "anvil.log", extra=["--gas-limit", str(DEEP_GAS)]) as anvil,
            JsonRpcClient(anvil) as anvil_rpc,
        ):
            fund(anvil_rpc, robot)
            theirs = deploy_code(anvil, robot, DEPLOY_RECURSE, RECURSE_RUNTIME)
            answers = {
                depth: (
                    call_recurse(f"{ledger.url}/rpc", ours, depth),
                    call_recurse(anvil, theirs, depth),
                )
                for depth in (1, 1024, 1025)
            }
        assert answers[1][0] == answers[1024][0] == "0x" + "00" * 31 + "01"
        assert answers[1025][0] == "0x"
        assert all(mine == node for mine, node in answers.values())
        assert ledger.process is not None
        assert ledger.process.poll() is None
    finally:
        ledger.stop()
