"""A forwarding proxy between a storage node and its ledger, for tests that act on what the
node sends (a transaction calling one contract function), never on a timer.

A test subclasses ``LedgerProxy`` and decides per exchange: forward it, hold it, or kill the
storage node instead of answering. ``storage_behind`` starts the node on the proxy's URL.
"""

from __future__ import annotations

import json
import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import httpx
import rlp
from eth_utils.crypto import keccak

from robocloud.identity import Identity
from robocloud.ingest import Ingest
from robocloud.ledger import JsonRpcClient
from robocloud.ledger.abi import ContractAbi, signature
from tests.bagfactory import START_NS, write_bag
from tests.conftest import ServiceFactory
from tests.integration.robocloud.ledger.nodes import ethereum_node
from tests.integration.services.ledger.conftest import ledger_fronting
from tests.integration.services.storage.test_ingest_http import Storage, approve
from tests.procs import ServiceProcess, free_port
from tests.scripted_http import Exchange, Reply, ScriptedServer, scripted_server
from tests.waiting import wait_for

HOP_BY_HOP = {"host", "connection", "keep-alive", "content-length", "transfer-encoding"}


def selector(contract: str, function: str) -> bytes:
    """The four bytes calldata starts with when it calls ``function`` of ``contract``."""
    return keccak(text=signature(ContractAbi.load(contract).functions[function]))[:4]


ADVERTISE = selector("Registry", "advertise")


def calldata(raw: bytes) -> bytes:
    """The ``data`` of a signed transaction: legacy (an RLP list) or typed (EIP-2718)."""
    if raw[0] >= 0xC0:
        return bytes(rlp.decode(raw)[5])
    fields = rlp.decode(raw[1:])
    return bytes(fields[6] if raw[0] == 1 else fields[7])


def rpc_calls(body: bytes) -> list[Any]:
    """The JSON-RPC calls of a request body, one or a batch (none when it is not JSON)."""
    try:
        message = json.loads(body)
    except ValueError:
        return []
    return message if isinstance(message, list) else [message]


def sends(body: bytes, function: bytes) -> bool:
    """Whether a JSON-RPC request sends a transaction whose calldata starts with ``function``."""
    return any(
        isinstance(call, dict)
        and call.get("method") == "eth_sendRawTransaction"
        and calldata(bytes.fromhex(str(call["params"][0]).removeprefix("0x")))[:4] == function
        for call in rpc_calls(body)
    )


class LedgerProxy:
    """Forwards every exchange to the ledger; subclasses override ``__call__`` to act on some."""

    def __init__(self, ledger: ServiceProcess) -> None:
        self.ledger = ledger
        self.upstream = httpx.Client(base_url=ledger.url, timeout=60)
        self.storage: ServiceProcess | None = None
        self.killed = threading.Event()
        self.lock = threading.Lock()

    def __call__(self, exchange: Exchange) -> Reply:
        return self.answer(self.forward(exchange))

    def forward(self, exchange: Exchange) -> httpx.Response:
        headers = {k: v for k, v in exchange.headers.items() if k not in HOP_BY_HOP}
        return self.upstream.request(
            exchange.method, exchange.path, headers=headers, content=exchange.body
        )

    @staticmethod
    def answer(response: httpx.Response) -> Reply:
        """The ledger's answer as the proxy's own (httpx has already decoded the body)."""
        dropped = HOP_BY_HOP | {"content-encoding"}
        kept = {k: v for k, v in response.headers.items() if k.lower() not in dropped}
        return response.status_code, kept, response.content

    def kill_storage(self) -> Reply:
        """SIGKILL the storage node; it gets no answer."""
        assert self.storage is not None
        assert self.storage.process is not None
        os.kill(self.storage.process.pid, signal.SIGKILL)
        self.killed.set()
        return None

    def wait_killed(self, what: str) -> None:
        """Wait until the storage node was killed on ``what`` and has exited."""
        wait_for(self.killed.is_set, what)
        assert self.storage is not None
        assert self.storage.process is not None
        self.storage.process.wait()


@contextmanager
def serving(proxy: LedgerProxy) -> Iterator[ScriptedServer]:
    """``proxy`` on a free loopback port until the block ends; its client to the ledger is
    closed after (its pooled connections otherwise outlive the test)."""
    with proxy.upstream, scripted_server(proxy, answer_audience=False) as server:
        yield server


def storage_behind(
    proxy: LedgerProxy,
    proxy_url: str,
    service_factory: ServiceFactory,
    cas: ServiceProcess,
    env: dict[str, str],
    *,
    port: int | None = None,
) -> ServiceProcess:
    """A storage node reaching its ledger through ``proxy`` (at ``proxy_url``), the
    knowledge follower off, with ``env`` on top, on ``port`` (a free one by default)."""
    base = {
        "ROBOCLOUD_LEDGER_URL": proxy_url,
        "ROBOCLOUD_CAS_URL": cas.url,
        "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
    }
    proxy.storage = service_factory("storage", {**base, **env}, port=port)
    return proxy.storage


Proxy = TypeVar("Proxy", bound=LedgerProxy)


@dataclass
class OnAnvil:
    """What ``anchoring_on_anvil`` started: anvil, the ledger fronting it, the storage node."""

    anvil_url: str
    anvil: JsonRpcClient
    ledger: ServiceProcess
    storage: ServiceProcess
    node: str


@contextmanager
def anchoring_on_anvil(
    make_proxy: Callable[[ServiceProcess, JsonRpcClient], Proxy],
    service_factory: ServiceFactory,
    tmp_path: Path,
    env: dict[str, str],
) -> Iterator[tuple[Proxy, OnAnvil]]:
    """anvil, a ledger fronting it that grants the storage role, cas, and a funded storage
    node anchoring 0.2 s epochs (retries from 0.2 s) through the proxy ``make_proxy``
    builds, with ``env`` on top."""
    with ethereum_node(tmp_path / "anvil.log") as anvil_url, JsonRpcClient(anvil_url) as anvil:
        storage_port = free_port()
        storage_url = f"http://127.0.0.1:{storage_port}"
        ledger = ledger_fronting(
            service_factory, anvil_url, anvil, tmp_path / "ledger", storage_url
        )
        cas = service_factory("cas")
        proxy = make_proxy(ledger, anvil)
        with serving(proxy) as server:
            base = {"ROBOCLOUD_STORAGE_EPOCH_S": "0.2", "ROBOCLOUD_STORAGE_ANCHOR_RETRY_S": "0.2"}
            storage = storage_behind(
                proxy, server.url, service_factory, cas, {**base, **env}, port=storage_port
            )
            node = str(httpx.get(f"{storage.url}/v1/node", timeout=10).json()["address"])
            anvil.request("hardhat_setBalance", [node, hex(10**18)])
            yield proxy, OnAnvil(anvil_url, anvil, ledger, storage, node)


def upload_imu_bag(storage: ServiceProcess, identity: Identity, bag: Path) -> tuple[str, str]:
    """Approve an Imu template, bind the bag's Imu topic to it and upload a 50-message bag;
    the template's id and the job's."""
    write_bag(bag, "ros1", 50, start_ns=START_NS)
    with Storage(storage.url, identity) as client, Ingest(storage.url, identity) as ingest:
        imu = approve(client, "sensor_msgs/msg/Imu")
        ingest.bind(imu, msgtype="sensor_msgs/msg/Imu")
        return imu, str(ingest.upload(bag)["id"])
