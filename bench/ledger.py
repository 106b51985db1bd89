"""Ledger throughput, event-index latency and restart time, against eth-tester in the same run.

1. Registration + advertisement throughput: robots sign their own transactions and send them
   to the service's ``/rpc`` (``eth_sendRawTransaction`` + ``eth_getTransactionReceipt``),
   against raw ``EthereumTester.send_transaction`` in this process doing the same calls on the
   same contracts. The issue asks for at least 0.7x.
2. Event-index queries: p50 of the index's ``eth_getLogs`` filter and of the advertisements
   read over 10,000 Advertised events (the issue asks for at most 5 ms), and the ratio against
   eth-tester's ``get_logs`` for the same query. eth-tester's ``get_logs`` is quadratic (1,000
   events took 82 s in ENVIRONMENT.md), so that ratio is taken on the events of part 1: the
   same query on the service's own index and on eth-tester's chain, which hold the same events.
   Against the index over 10,000 events the same eth-tester time gives a lower bound.
3. Restart: reopening the chain store and a whole service restart, with the chain of part 1.

    python bench/ledger.py [--robots 60] [--events 10000] [--queries 200]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "clients")]

from eth_abi.abi import encode  # noqa: E402
from eth_tester import EthereumTester  # noqa: E402
from eth_utils.crypto import keccak  # noqa: E402

from robocloud.cid import CID  # noqa: E402
from robocloud.client import ServiceClient  # noqa: E402
from robocloud.identity import Identity  # noqa: E402
from robocloud.ledger.abi import ContractAbi  # noqa: E402
from services.ledger.chain import EmbeddedChain  # noqa: E402
from services.ledger.contracts import artifact  # noqa: E402
from services.ledger.encoding import LogEntry  # noqa: E402
from services.ledger.index import EventIndex, LogFilter  # noqa: E402
from tests.procs import ServiceProcess  # noqa: E402

REGISTRY = ContractAbi.load("Registry")
ADVERTISED = REGISTRY.event_topic("Advertised")
GAS = 300_000
GAS_PRICE = 2 * 10**9


def cid_of(n: int) -> bytes:
    return bytes.fromhex("01551220") + keccak(n.to_bytes(8, "big"))


def robot_calls(index: int) -> list[bytes]:
    """What robot ``index`` sends: register, then advertise one CID."""
    return [
        REGISTRY.encode_call("register", cid_of(10**6 + index)),
        REGISTRY.encode_call("advertise", cid_of(index), b""),
    ]


def p50_ms(action: Callable[[], object], rounds: int) -> float:
    times = []
    for _ in range(rounds):
        started = time.perf_counter()
        action()
        times.append(time.perf_counter() - started)
    return statistics.median(times) * 1000


# ----- part 1: the service -----


def rpc(client: httpx.Client, method: str, params: list[Any]) -> Any:
    answer = client.post(
        "/rpc", json={"jsonrpc": "2.0", "id": 1, "method": method, "params": params}
    )
    body = answer.json()
    if "error" in body:
        raise RuntimeError(f"{method}: {body['error']}")
    return body["result"]


def service_throughput(process: ServiceProcess, robots: list[Identity]) -> float:
    """Transactions per second through /rpc, signing included."""
    registry = httpx.get(f"{process.url}/v1/contracts").json()["contracts"]["Registry"]["address"]
    for robot in robots:
        with ServiceClient(process.url, robot) as client:
            client.post_json("/v1/faucet", {"address": robot.address})
    sent = 0
    with httpx.Client(base_url=process.url, timeout=30) as client:
        started = time.perf_counter()
        for index, robot in enumerate(robots):
            for nonce, data in enumerate(robot_calls(index)):
                transaction = {"chainId": 1337, "nonce": nonce, "gas": GAS, "gasPrice": GAS_PRICE}
                transaction |= {"to": registry, "data": data, "value": 0}
                raw = robot.account.sign_transaction(transaction).raw_transaction
                tx_hash = rpc(client, "eth_sendRawTransaction", ["0x" + bytes(raw).hex()])
                receipt = rpc(client, "eth_getTransactionReceipt", [tx_hash])
                if receipt["status"] != "0x1":
                    raise RuntimeError(f"transaction {tx_hash} failed")
                sent += 1
        return sent / (time.perf_counter() - started)


# ----- part 1: eth-tester -----


def tester_throughput(robots: list[Identity]) -> tuple[float, EthereumTester, str]:
    """The same transactions with raw eth-tester, signing included; the tester and Registry."""
    tester = EthereumTester()
    funder = tester.get_accounts()[0]
    deploy = tester.send_transaction(
        {"from": funder, "data": artifact("Registry")["bytecode"], "gas": 5_000_000}
    )
    registry = tester.get_transaction_receipt(deploy)["contract_address"]
    for robot in robots:
        tester.add_account("0x" + robot.account.key.hex())
        tester.send_transaction(
            {"from": funder, "to": robot.address, "value": 10**18, "gas": 21_000}
        )
    sent = 0
    started = time.perf_counter()
    for index, robot in enumerate(robots):
        for data in robot_calls(index):
            tx_hash = tester.send_transaction(
                {
                    "from": robot.address,
                    "to": registry,
                    "data": "0x" + data.hex(),
                    "gas": GAS,
                    "gas_price": GAS_PRICE,
                }
            )
            if tester.get_transaction_receipt(tx_hash)["status"] != 1:
                raise RuntimeError(f"eth-tester transaction {tx_hash} failed")
            sent += 1
    return sent / (time.perf_counter() - started), tester, registry


# ----- part 2: the index -----


def advertised_log(number: int, advertiser: bytes, registry: bytes) -> LogEntry:
    """An Advertised log exactly as the Registry emits it (same ABI encoding and topics)."""
    cid = cid_of(number % 1000)
    data = encode(
        ["bytes", "bytes", "bool", "uint64"], [cid, b"", number < 1000, 1_800_000_000 + number]
    )
    return LogEntry(
        block_number=number + 1,
        block_hash=keccak(number.to_bytes(8, "big")),
        tx_hash=keccak(b"tx" + number.to_bytes(8, "big")),
        tx_index=0,
        log_index=0,
        address=registry,
        topics=(ADVERTISED, keccak(cid), b"\x00" * 12 + advertiser),
        data=data,
    )


def filled_index(directory: Path, events: int) -> tuple[EventIndex, bytes]:
    registry = bytes.fromhex("5f" * 20)
    directory.mkdir(parents=True, exist_ok=True)
    index = EventIndex(directory / "index.sqlite", "0x" + registry.hex(), "0x" + "6e" * 20)
    advertisers = [Identity.generate() for _ in range(20)]
    for number in range(events):
        advertiser = bytes.fromhex(advertisers[number % 20].address[2:])
        entry = advertised_log(number, advertiser, registry)
        index.add_block(entry.block_number, entry.block_hash, [entry])
    return index, registry


def index_queries(index: EventIndex, registry: bytes, events: int, rounds: int) -> dict[str, float]:
    """p50 of a topic query (one CID's advertisements) through both read paths."""
    cid = cid_of(7)
    topic_filter = LogFilter(
        from_block=0,
        to_block=events + 1,
        addresses=(registry,),
        topics=((ADVERTISED,), (keccak(cid),)),
    )
    found = len(index.logs(topic_filter))
    return {
        "eth_getLogs filter": p50_ms(lambda: index.logs(topic_filter), rounds),
        "advertisements by cid": p50_ms(lambda: index.advertisements(cid, None, 0, 100), rounds),
        "matches": found,
    }


def tester_logs_ms(tester: EthereumTester, registry: str, cid: bytes, rounds: int) -> float:
    topics = ["0x" + ADVERTISED.hex(), "0x" + keccak(cid).hex()]
    return p50_ms(lambda: tester.get_logs(from_block=0, address=registry, topics=topics), rounds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--robots", type=int, default=60)
    parser.add_argument("--events", type=int, default=10_000)
    parser.add_argument("--queries", type=int, default=200)
    args = parser.parse_args()
    robots = [Identity.generate() for _ in range(args.robots)]
    txs = 2 * args.robots

    with tempfile.TemporaryDirectory() as tmp:
        data_dir = Path(tmp) / "ledger"
        env = {
            "ROBOCLOUD_LEDGER_ADMIN_PASSPHRASE": "bench",
            "ROBOCLOUD_LEDGER_FAUCET_PER_MINUTE": "100000",
        }
        process = ServiceProcess("ledger", data_dir, env).start()
        try:
            ours = service_throughput(process, robots)
            stopped = time.perf_counter()
            process.restart()
            restart_s = time.perf_counter() - stopped
            reader = httpx.Client(base_url=process.url)
            http_ms = p50_ms(
                lambda: reader.get(
                    "/v1/advertisements", params={"cid": str(CID.from_bytes(cid_of(7)))}
                ),
                args.queries,
            )
            head = httpx.get(f"{process.url}/v1/blocks/latest").json()["number"]
            described = httpx.get(f"{process.url}/v1/contracts").json()["contracts"]
            contracts = {name: entry["address"] for name, entry in described.items()}
            reader.close()
        finally:
            process.stop()
        started = time.perf_counter()
        reopened = EmbeddedChain(data_dir / "chain.sqlite")
        reopen_ms = (time.perf_counter() - started) * 1000
        reopened.close()

        baseline, tester, registry = tester_throughput(robots)
        print(f"registration + advertisement, {txs} transactions each, signing included")
        print(f"  ledger /rpc         {ours:7.1f} tx/s")
        print(f"  raw eth-tester      {baseline:7.1f} tx/s")
        print(f"  ratio               {ours / baseline:7.2f}x   (target >= 0.70x)")

        same = EventIndex(data_dir / "index.sqlite", contracts["Registry"], contracts["AnchorLog"])
        ours_small = index_queries(
            same, bytes.fromhex(contracts["Registry"][2:]), head, args.queries
        )
        theirs_ms = tester_logs_ms(tester, registry, cid_of(7), max(args.queries // 20, 3))
        same.close()
        index, big_registry = filled_index(Path(tmp) / "big", args.events)
        big = index_queries(index, big_registry, args.events, args.queries)
        index.close()

    print(f"event index, one CID's Advertised events (p50 of {args.queries} queries)")
    print(
        f"  over {args.events} events: eth_getLogs filter {big['eth_getLogs filter']:.3f} ms, "
        f"advertisements by cid {big['advertisements by cid']:.3f} ms   (target <= 5 ms)"
    )
    print(
        f"  over part 1's {head} blocks: index {ours_small['eth_getLogs filter']:.3f} ms, "
        f"eth-tester get_logs {theirs_ms:.1f} ms, "
        f"ratio {theirs_ms / ours_small['eth_getLogs filter']:.0f}x faster "
        f"(eth-tester is quadratic: not run at {args.events})"
    )
    print(
        f"  over {args.events} events: at least {theirs_ms / big['eth_getLogs filter']:.0f}x "
        f"faster than eth-tester (its get_logs measured over part 1's {head} blocks, a lower "
        "bound: its cost only grows with the events it holds)"
    )
    print(f"  GET /v1/advertisements?cid= over HTTP, part 1's events: p50 {http_ms:.2f} ms")
    print(
        f"restart with {head} blocks: reopen chain store {reopen_ms:.1f} ms, "
        f"whole service stop+start until ready {restart_s:.2f} s"
    )


if __name__ == "__main__":
    main()
