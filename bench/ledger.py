"""Ledger speed against anvil in the same run, event-index latency and restart time.

``transfers`` (the default part) answers issue 17:

1. Sequential sign-send-receipt: one robot signs a transfer, sends it with
   ``eth_sendRawTransaction`` and asks for its receipt (until it has one: anvil mines after
   answering), again and again; through the ledger's ``/rpc`` and through a fresh anvil on
   the same machine, in alternating rounds so that both see the same machine load. The
   ratio is the ledger's rate over anvil's (goal: at least 0.5x).
2. Concurrency: 50 transactions sent at once (50 robots, then one robot's 50 nonces in a
   shuffled order, which the pending pool puts back in order), the time until all are
   accepted and until all are mined (goal: within 2 s).
3. Where a transaction's time goes: the embedded chain in this process, each stage timed
   (sender recovery, validity checks, execution, tries and block assembly, writing the
   block, the fsync of the commit, the event index), and HTTP as the rest of the time one
   transaction takes through /rpc; and the ceiling this puts on the ratio: what it would be
   if the ledger's HTTP cost no more than anvil's whole cycle, the chain's work being added.
4. External-node mode: the same rounds with the ledger forwarding ``/rpc`` to its own anvil,
   against a second anvil: what the service costs as a forwarder, with no chain work
   (``external`` runs this step alone).

``calls`` answers the eth_call latency that storage's proof verification pays: the p50 of one
``AnchorLog.anchorAt`` view call at ``latest`` through ``/rpc`` (the SDK's JSON-RPC client, as
``robocloud verify`` sends it), beside ``eth_chainId`` through the same client (the HTTP
floor: an answer with no chain work) and the same call on the embedded chain in this process.

``flood`` answers what strangers' free calls cost an honest robot: the p50 of a transfer, of a
balance read and of an ``eth_call`` of its own, quiet and while ``--flooders`` clients (one
address, another than the robot's) each send a looping ``eth_call`` again and again (each runs
to the EVM timeout), and how the flooding calls were answered.

``index`` is the earlier benchmark: registration + advertisement throughput against raw
eth-tester, the event index over 10,000 events against eth-tester's ``get_logs``, restart.

    python bench/ledger.py [transfers|external|calls|index|flood] [--rounds 5] [--transactions 100]
        [--calls 1000] [--flooders 60]
"""

from __future__ import annotations

import argparse
import os
import random
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
os.environ.setdefault("ETH_HASH_BACKEND", "pysha3")  # as the service runs (its __main__)

from eth_abi.abi import encode  # noqa: E402
from eth_tester import EthereumTester  # noqa: E402
from eth_utils.crypto import keccak  # noqa: E402

from robocloud.cid import CID  # noqa: E402
from robocloud.client import ServiceClient  # noqa: E402
from robocloud.identity import Identity  # noqa: E402
from robocloud.ledger.abi import ContractAbi  # noqa: E402
from services.ledger.chain import CallRequest, EmbeddedChain  # noqa: E402
from services.ledger.contracts import artifact  # noqa: E402
from services.ledger.encoding import LogEntry  # noqa: E402
from services.ledger.index import EventIndex, LogFilter  # noqa: E402
from tests.integration.robocloud.ledger.nodes import ethereum_node  # noqa: E402
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


def index_part(args: argparse.Namespace) -> None:
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


# ----- transfers: the ledger against anvil -----


class Node:
    """One JSON-RPC endpoint over one kept-alive connection."""

    def __init__(self, name: str, url: str) -> None:
        self.name = name
        self.url = url
        self.client = httpx.Client(timeout=30)

    def call(self, method: str, params: list[Any]) -> Any:
        body = self.client.post(
            self.url, json={"jsonrpc": "2.0", "id": 1, "method": method, "params": params}
        ).json()
        if "error" in body:
            raise RuntimeError(f"{self.name} {method}: {body['error']}")
        return body["result"]

    def receipt(self, tx_hash: str) -> dict[str, Any]:
        while True:
            found = self.call("eth_getTransactionReceipt", [tx_hash])
            if found is not None:
                if found["status"] != "0x1":
                    raise RuntimeError(f"{self.name}: {tx_hash} failed")
                return dict(found)


def transfer(robot: Identity, nonce: int) -> str:
    signed = robot.account.sign_transaction(
        {
            "chainId": 1337,
            "nonce": nonce,
            "gas": 21_000,
            "maxFeePerGas": 10**11,
            "maxPriorityFeePerGas": 10**9,
            "to": "0x" + "22" * 20,
            "value": 1,
        }
    )
    return "0x" + bytes(signed.raw_transaction).hex()


def sequential_rate(node: Node, robot: Identity, count: int) -> float:
    """Transactions per second, each signed, sent and its receipt read before the next."""
    nonce = int(node.call("eth_getTransactionCount", [robot.address, "latest"]), 16)
    started = time.perf_counter()
    for offset in range(count):
        node.receipt(node.call("eth_sendRawTransaction", [transfer(robot, nonce + offset)]))
    return count / (time.perf_counter() - started)


def alternating_rates(
    ledger: Node, anvil: Node, robots: list[Identity], args: argparse.Namespace
) -> tuple[list[float], list[float]]:
    """Each node's sequential rate per round, the two taking turns at going first so that
    both see the same machine load; round ``r`` uses ``robots[2r]`` and ``robots[2r + 1]``."""
    ours, theirs = [], []
    for round_ in range(args.rounds):
        pair = (ledger, anvil) if round_ % 2 == 0 else (anvil, ledger)
        rates = {
            node.name: sequential_rate(node, robots[2 * round_ + i], args.transactions)
            for i, node in enumerate(pair)
        }
        ours.append(rates[ledger.name])
        theirs.append(rates[anvil.name])
    return ours, theirs


def concurrent_seconds(url: str, raws: list[str]) -> tuple[float, float]:
    """Send ``raws`` at once, one connection each; seconds until all were accepted, and
    until all were mined."""
    from concurrent.futures import ThreadPoolExecutor

    nodes = [Node("node", url) for _ in raws]
    started = time.perf_counter()
    with ThreadPoolExecutor(len(raws)) as pool:
        hashes = list(
            pool.map(
                lambda pair: pair[0].call("eth_sendRawTransaction", [pair[1]]),
                zip(nodes, raws, strict=True),
            )
        )
        accepted = time.perf_counter() - started
        list(pool.map(lambda pair: pair[0].receipt(pair[1]), zip(nodes, hashes, strict=True)))
    return accepted, time.perf_counter() - started


def funded_robots(ledger_url: str, anvil: Node | None, count: int) -> list[Identity]:
    """Robots funded by the ledger's faucet, and on ``anvil`` too when there is one."""
    robots = [Identity.generate() for _ in range(count)]
    for robot in robots:
        with ServiceClient(ledger_url, robot) as client:
            client.post_json("/v1/faucet", {"address": robot.address})
        if anvil is not None:
            anvil.call("anvil_setBalance", [robot.address, hex(10**20)])
    return robots


def breakdown(count: int) -> dict[str, float]:
    """Milliseconds per transaction in each stage of the embedded chain, in this process."""
    import eth.db.chain as chaindbs
    import eth.vm.base as vms

    from services.ledger import encoding
    from services.ledger.chaindb import DevChain

    timings: dict[str, float] = {}

    def timed(stage: str, function: Callable[..., Any]) -> Callable[..., Any]:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            started = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                timings[stage] = timings.get(stage, 0.0) + time.perf_counter() - started

        return wrapper

    stages: list[tuple[Any, str, str]] = [
        (EmbeddedChain, "decode", "sender recovery (decode)"),
        (vms.VM, "build_state", "building the head's state"),
        (EmbeddedChain, "_check", "validity checks"),
        (vms.VM, "apply_all_transactions", "execution"),
        (vms.VM, "set_block_transactions_and_withdrawals", "transaction and receipt tries"),
        (vms.VM, "finalize_block", "state trie and block sealing"),
        (chaindbs.ChainDB, "persist_block", "writing the block"),
        (DevChain, "create_header_from_parent", "next pending header"),
    ]
    robot = Identity.generate()
    address = bytes.fromhex(robot.address[2:])
    with tempfile.TemporaryDirectory() as tmp:
        genesis = {address: {"balance": 10**24, "nonce": 0, "code": b"", "storage": {}}}
        chain = EmbeddedChain(Path(tmp) / "chain.sqlite", genesis)
        index = EventIndex(Path(tmp) / "index.sqlite", "0x" + "11" * 20, "0x" + "22" * 20)
        chain.on_block(
            timed(
                "event index",
                lambda mined: index.add_block(
                    mined.block.number,
                    mined.block.hash,
                    encoding.block_logs(mined.block, mined.receipts),
                ),
            )
        )
        raws = [bytes.fromhex(transfer(robot, nonce)[2:]) for nonce in range(2 * count)]
        store = chain._db.store
        connection = store.connection

        class TimedCommit:
            def execute(self, sql: str, *args: Any) -> Any:
                if sql != "COMMIT":
                    return connection.execute(sql, *args)
                started = time.perf_counter()
                try:
                    return connection.execute(sql, *args)
                finally:
                    timings["commit (fsync)"] = timings.get("commit (fsync)", 0.0) + (
                        time.perf_counter() - started
                    )

        for raw in raws[:count]:  # warm up
            chain.send_raw_transaction(raw)
        timings.clear()
        originals = [(owner, name, owner.__dict__[name]) for owner, name, _ in stages]
        for owner, name, stage in stages:
            original = owner.__dict__[name]
            if isinstance(original, classmethod):
                setattr(owner, name, classmethod(timed(stage, original.__func__)))
            else:
                setattr(owner, name, timed(stage, original))
        store.connection = TimedCommit()  # type: ignore[assignment]
        started = time.perf_counter()
        try:
            for raw in raws[count:]:
                submitted = chain.send_raw_transaction(raw)
                located = chain.locate(submitted.hash)
                assert located is not None
                encoding.receipt(
                    located.block, chain.receipts(located.block), 0, located.transaction
                )
            total = time.perf_counter() - started
        finally:
            for owner, name, original in originals:
                setattr(owner, name, original)
            store.connection = connection
        index.close()
        chain.close()
    per_transaction = {stage: seconds / count * 1000 for stage, seconds in timings.items()}
    per_transaction["in-process total"] = total / count * 1000
    return per_transaction


def transfers_part(args: argparse.Namespace) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        env = {
            "ROBOCLOUD_LEDGER_ADMIN_PASSPHRASE": "bench",
            "ROBOCLOUD_LEDGER_FAUCET_PER_MINUTE": "100000",
        }
        process = ServiceProcess("ledger", Path(tmp) / "ledger", env).start()
        try:
            with ethereum_node(Path(tmp) / "anvil.log") as anvil_url:
                ledger = Node("ledger", f"{process.url}/rpc")
                anvil = Node("anvil", anvil_url)
                robots = funded_robots(process.url, anvil, 2 + 2 * args.rounds)
                print(f"sequential sign-send-receipt transfers, {args.transactions} per round")
                ours, theirs = alternating_rates(ledger, anvil, robots, args)
                for round_, (mine, its) in enumerate(zip(ours, theirs, strict=True)):
                    print(
                        f"  round {round_ + 1}: ledger {mine:6.1f} tx/s, "
                        f"anvil {its:6.1f} tx/s, ratio {mine / its:.2f}x"
                    )
                ratio = statistics.median(o / t for o, t in zip(ours, theirs, strict=True))
                print(
                    f"  median: ledger {statistics.median(ours):.1f} tx/s, anvil "
                    f"{statistics.median(theirs):.1f} tx/s, ratio {ratio:.2f}x (goal >= 0.50x)"
                )
                print("50 transactions at once (accepted / mined, seconds; goal: mined <= 2 s)")
                many = funded_robots(process.url, anvil, 50)
                for node_name, url in (("ledger", f"{process.url}/rpc"), ("anvil", anvil_url)):
                    raws = [transfer(robot, 0) for robot in many]
                    accepted, mined = concurrent_seconds(url, raws)
                    print(f"  {node_name:6s} 50 robots:            {accepted:5.2f} / {mined:5.2f}")
                single = robots[-1]
                for node in (ledger, anvil):
                    start = int(
                        node.call("eth_getTransactionCount", [single.address, "latest"]), 16
                    )
                    nonces = list(range(start, start + 50))
                    random.Random(17).shuffle(nonces)
                    raws = [transfer(single, nonce) for nonce in nonces]
                    url = f"{process.url}/rpc" if node is ledger else anvil_url
                    accepted, mined = concurrent_seconds(url, raws)
                    print(
                        f"  {node.name:6s} one robot, 50 shuffled nonces: "
                        f"{accepted:5.2f} / {mined:5.2f}"
                    )
                http_ms = 1000 / statistics.median(ours)
                anvil_ms = 1000 / statistics.median(theirs)
        finally:
            process.stop()
    external_node_part(args)
    stages = breakdown(args.transactions)
    print("where a transaction's time goes (ms per transaction)")
    for stage, ms in stages.items():
        print(f"  {stage:32s} {ms:6.3f}")
    signer = Identity.generate()
    started = time.perf_counter()
    for nonce in range(args.transactions):
        transfer(signer, nonce)
    signing_ms = (time.perf_counter() - started) / args.transactions * 1000
    rest = http_ms - stages["in-process total"] - signing_ms
    print(f"  {'signing (the client, eth-account)':32s} {signing_ms:6.3f}")
    print(f"  {'through /rpc (median round)':32s} {http_ms:6.3f}")
    print(f"  {'HTTP and JSON, both requests':32s} {rest:6.3f}   (the difference)")
    chain_ms = stages["in-process total"]
    print(
        f"ceiling on py-evm: with HTTP as cheap as anvil's whole cycle ({anvil_ms:.3f} ms), the "
        f"chain's {chain_ms:.3f} ms alone caps the ratio at "
        f"{anvil_ms / (anvil_ms + chain_ms):.2f}x; 0.5x needs the chain within anvil's cycle"
    )


def external_node_part(args: argparse.Namespace) -> None:
    """The same sequential rounds with the ledger in external-node mode over its own anvil,
    against a second, fresh anvil: what ``/rpc`` costs as a forwarder, chain work aside."""
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        with (
            ethereum_node(work / "behind.log") as behind_url,
            ethereum_node(work / "direct.log") as direct_url,
        ):
            behind, direct = Node("behind", behind_url), Node("anvil", direct_url)
            admin = Identity.generate()
            admin.save(work / "ledger" / "keys" / "admin.json", "bench", scrypt_n=2**14)
            robots = [Identity.generate() for _ in range(2 * args.rounds)]
            for identity in (admin, *robots):
                for node in (behind, direct):
                    node.call("anvil_setBalance", [identity.address, hex(10**21)])
            env = {
                "ROBOCLOUD_LEDGER_ADMIN_PASSPHRASE": "bench",
                "ROBOCLOUD_LEDGER_RPC_URL": behind_url,
            }
            process = ServiceProcess("ledger", work / "ledger", env).start()
            try:
                ledger = Node("ledger", f"{process.url}/rpc")
                ours, theirs = alternating_rates(ledger, direct, robots, args)
                ratios = [mine / its for mine, its in zip(ours, theirs, strict=True)]
                print(
                    "external-node mode (the ledger forwarding to its own anvil) against anvil: "
                    f"median ratio {statistics.median(ratios):.2f}x "
                    f"(rounds {min(ratios):.2f}-{max(ratios):.2f}x)"
                )
            finally:
                process.stop()


def calls_part(args: argparse.Namespace) -> None:
    from robocloud.ledger import LedgerService
    from robocloud.ledger.rpc import JsonRpcClient
    from robocloud.proofs import anchor_at_call

    with tempfile.TemporaryDirectory() as tmp:
        env = {"ROBOCLOUD_LEDGER_ADMIN_PASSPHRASE": "bench", "ROBOCLOUD_LEDGER_GRANT_ROLES": ""}
        process = ServiceProcess("ledger", Path(tmp) / "ledger", env).start()
        try:
            with LedgerService(process.url) as service:
                anchor_log = service.contracts().anchor_log
            call = anchor_at_call(anchor_log, "0x" + "33" * 20, 1)
            with JsonRpcClient(f"{process.url}/rpc") as rpc:
                for _ in range(50):  # warm up: connections, caches, worker threads
                    rpc.request("eth_call", [call, "latest"])
                over_rpc = p50_ms(lambda: rpc.request("eth_call", [call, "latest"]), args.calls)
                floor = p50_ms(lambda: rpc.request("eth_chainId", []), args.calls)
        finally:
            process.stop()
        chain = EmbeddedChain(Path(tmp) / "ledger" / "chain.sqlite")
        try:
            request = CallRequest(
                b"\x00" * 20, bytes.fromhex(call["to"][2:]), bytes.fromhex(call["data"][2:])
            )
            for _ in range(50):
                chain.call(request, "latest")
            in_process = p50_ms(lambda: chain.call(request, "latest"), args.calls)
        finally:
            chain.close()
    print(f"AnchorLog.anchorAt eth_call at latest, p50 of {args.calls} (ms)")
    print(f"  through /rpc (SDK client)        {over_rpc:6.3f}   (target well under 1.5 ms)")
    print(f"  eth_chainId through /rpc         {floor:6.3f}   (HTTP and JSON, no chain work)")
    print(f"  EmbeddedChain.call in process    {in_process:6.3f}")


# ----- flood: transactions and reads while strangers' calls loop -----

FLOODER = "127.0.0.2"
"""The flood's address: one client, another than the honest robot's (127.0.0.1)."""
LOOPING_CALL = {"data": "0x5b600056"}
"""Init code that loops forever (JUMPDEST PUSH1 0 JUMP): every such eth_call runs until the
EVM timeout."""


def latencies_ms(node: Node, robot: Identity, count: int) -> tuple[float, float, float, int]:
    """p50 of a sign-send-receipt transfer, of an ``eth_getBalance`` and of an ``eth_call``
    (to an address with no code), in ms; and how many of the calls were refused."""
    nonce = int(node.call("eth_getTransactionCount", [robot.address, "latest"]), 16)
    sends, reads, calls = [], [], []
    refused = 0
    for offset in range(count):
        started = time.perf_counter()
        node.receipt(node.call("eth_sendRawTransaction", [transfer(robot, nonce + offset)]))
        sends.append(time.perf_counter() - started)
        started = time.perf_counter()
        node.call("eth_getBalance", [robot.address, "latest"])
        reads.append(time.perf_counter() - started)
        started = time.perf_counter()
        try:
            node.call("eth_call", [{"to": "0x" + "22" * 20}, "latest"])
        except RuntimeError:
            refused += 1
        calls.append(time.perf_counter() - started)
    send, read, call = (statistics.median(times) * 1000 for times in (sends, reads, calls))
    return send, read, call, refused


def flood_part(args: argparse.Namespace) -> None:
    """Transfers and reads with no calls running, then while ``--flooders`` clients each send
    a looping ``eth_call`` over and over; the ratio is what the flood costs an honest robot."""
    import threading

    with tempfile.TemporaryDirectory() as tmp:
        env = {
            "ROBOCLOUD_LEDGER_ADMIN_PASSPHRASE": "bench",
            "ROBOCLOUD_LEDGER_FAUCET_PER_MINUTE": "100000",
            "ROBOCLOUD_LEDGER_GRANT_ROLES": "",
        }
        process = ServiceProcess("ledger", Path(tmp) / "ledger", env).start()
        stop = threading.Event()
        answers: dict[str, int] = {}
        rpc_url = f"{process.url}/rpc"

        def flood() -> None:
            payload = {"jsonrpc": "2.0", "id": 1, "method": "eth_call", "params": [LOOPING_CALL]}
            from_flooder = httpx.HTTPTransport(local_address=FLOODER)
            with httpx.Client(transport=from_flooder, timeout=120) as client:
                while not stop.is_set():
                    error = client.post(rpc_url, json=payload).json().get("error", {})
                    key = f"{error.get('code')} {error.get('message', '')[:40]}"
                    answers[key] = answers.get(key, 0) + 1

        flooders = [threading.Thread(target=flood) for _ in range(args.flooders)]
        try:
            node = Node("ledger", rpc_url)
            quiet_robot, flood_robot = funded_robots(process.url, None, 2)
            quiet = latencies_ms(node, quiet_robot, args.transactions)
            for flooder in flooders:
                flooder.start()
            time.sleep(1)
            flooded = latencies_ms(node, flood_robot, args.transactions)
        finally:
            stop.set()
            for flooder in flooders:
                flooder.join()
            process.stop()
    print(
        f"{args.transactions} transfers and balance reads, p50 ms: quiet / during a flood of "
        f"{args.flooders} clients looping eth_call"
    )
    print(
        f"  transfer (sign, send, receipt)  {quiet[0]:7.2f} / {flooded[0]:7.2f}   "
        f"{flooded[0] / quiet[0]:5.1f}x"
    )
    print(
        f"  eth_getBalance                  {quiet[1]:7.2f} / {flooded[1]:7.2f}   "
        f"{flooded[1] / quiet[1]:5.1f}x"
    )
    print(
        f"  eth_call, another client's      {quiet[2]:7.2f} / {flooded[2]:7.2f}   "
        f"{flooded[2] / quiet[2]:5.1f}x   refused {quiet[3]} / {flooded[3]}"
    )
    print("  the flooding calls' answers: " + ", ".join(f"{n} x {k}" for k, n in answers.items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument(
        "part",
        nargs="?",
        choices=("transfers", "external", "calls", "index", "flood"),
        default="transfers",
    )
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--transactions", type=int, default=100)
    parser.add_argument("--robots", type=int, default=60)
    parser.add_argument("--events", type=int, default=10_000)
    parser.add_argument("--queries", type=int, default=200)
    parser.add_argument("--calls", type=int, default=1000)
    parser.add_argument("--flooders", type=int, default=60)
    args = parser.parse_args()
    if args.part == "transfers":
        transfers_part(args)
    elif args.part == "external":
        external_node_part(args)
    elif args.part == "calls":
        calls_part(args)
    elif args.part == "flood":
        flood_part(args)
    else:
        index_part(args)


if __name__ == "__main__":
    main()
