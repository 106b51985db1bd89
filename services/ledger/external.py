"""External-node mode: the ledger service in front of any Ethereum JSON-RPC node.

With ``ROBOCLOUD_LEDGER_RPC_URL`` the service runs no chain of its own. It attaches to the
contracts at ``ROBOCLOUD_LEDGER_REGISTRY_ADDRESS`` / ``ROBOCLOUD_LEDGER_ANCHOR_LOG_ADDRESS``,
or deploys them once with the operator's admin key (which must hold ether on that chain) and
remembers where in ``contracts.json``. ``ROBOCLOUD_LEDGER_REGISTRATION_MODE`` is applied at
every start where that key is the Registry's admin; otherwise a Registry in another mode stops
the start (``contracts.must_switch_mode``). ``/rpc`` forwards the standard namespaces (``eth_``,
``net_``, ``web3_``) and nothing else, so a node's administrative or cheat methods
(``anvil_*``, ``debug_*``, ``personal_*``) are never exposed through the service; it relays
from the event loop (``forwarding``).

The event index follows the node by polling ``eth_getLogs`` for the two contracts in bounded
block ranges, ``confirmations`` blocks behind the head. Before each round it checks that the
last indexed block is still canonical; after a reorganisation it rewinds and re-reads. The
node's logs are its word: a malformed one, or one it was not asked for, stops the round at
its page, which is logged and asked again next round (``poll_once``).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import anyio
from eth_utils.address import is_address, to_checksum_address

from robocloud.errors import InvalidAnswerError, shown_text
from robocloud.identity import Identity
from robocloud.ledger import (
    ContractAbi,
    ContractAddresses,
    JsonRpcClient,
    Ledger,
    RpcError,
    Transactor,
)
from robocloud.ledger.abi import check_block, check_hash
from robocloud.ledger.transactions import quantity
from services.common.durable import atomic_write
from services.ledger.contracts import Deployment, artifact, must_switch_mode
from services.ledger.encoding import LogEntry
from services.ledger.forwarding import not_forwarded
from services.ledger.index import EventIndex
from services.ledger.node import FaucetUnavailable
from services.ledger.operator import admin_keystore, load_or_create, passphrase
from services.ledger.rpc import COSTLY_METHODS, Dispatcher, RpcFailure
from services.ledger.settings import LedgerSettings

log = logging.getLogger("robocloud.ledger.external")

REORG_DEPTH = 64
DEPLOYMENT_FILE = "contracts.json"
MAX_PAGES_PER_ROUND = 50
"""Ranges of ``ledger_log_page_blocks`` one indexing round asks for at most. A round runs on
a thread that start and shutdown wait for, so a head far ahead (after a long downtime, or a
node that says its head is near 2^63) is caught up over many short rounds, not one endless
one."""


class ExternalLedger:
    """The contracts, index and JSON-RPC of a chain served by another node."""

    def __init__(self, settings: LedgerSettings, data_dir: Path, secret: str | None) -> None:
        assert settings.ledger_rpc_url is not None
        self.settings = settings
        self.rpc = JsonRpcClient(settings.ledger_rpc_url)
        self.chain_id = quantity(self.rpc.request("eth_chainId", []))
        self.deployment = self._attach_or_deploy(data_dir, secret)
        self._apply_registration_mode(data_dir, secret)
        self.index = EventIndex(
            data_dir / "index.sqlite", self.deployment.registry, self.deployment.anchor_log
        )
        self.dispatcher = Dispatcher({}, fallback=self.forward, costly=COSTLY_METHODS)
        self.index_round()
        log.info(
            "following external node",
            extra={"chain_id": self.chain_id, **self.deployment.addresses()},
        )

    # ----- contracts -----

    def _attach_or_deploy(self, data_dir: Path, secret: str | None) -> Deployment:
        registry = self.settings.ledger_registry_address
        anchor_log = self.settings.ledger_anchor_log_address
        if registry or anchor_log:
            if not (registry and is_address(registry) and anchor_log and is_address(anchor_log)):
                raise ValueError("set both LEDGER_REGISTRY_ADDRESS and LEDGER_ANCHOR_LOG_ADDRESS")
            deployment = Deployment(
                str(to_checksum_address(registry)), str(to_checksum_address(anchor_log))
            )
        else:
            deployment = self._remembered(data_dir) or self._deploy(data_dir, secret)
        for name, address in deployment.addresses().items():
            if self.rpc.request("eth_getCode", [address, "latest"]) in ("0x", "0x0", None):
                raise ValueError(f"no {name} contract at {address} on chain {self.chain_id}")
        return deployment

    def _remembered(self, data_dir: Path) -> Deployment | None:
        path = data_dir / DEPLOYMENT_FILE
        if not path.exists():
            return None
        stored = json.loads(path.read_text())
        if stored.get("chain_id") != self.chain_id:
            raise ValueError(
                f"{path} records a deployment on chain {stored.get('chain_id')}, "
                f"but the node serves chain {self.chain_id}"
            )
        return Deployment(stored["Registry"], stored["AnchorLog"])

    def _deploy(self, data_dir: Path, secret: str | None) -> Deployment:
        admin = load_or_create(data_dir, passphrase(data_dir, secret)).admin
        transactor = Transactor(self.rpc, admin)
        registry = transactor.deploy(ContractAbi.load("Registry"), artifact("Registry")["bytecode"])
        assert registry.contract_address is not None
        anchor_log = transactor.deploy(
            ContractAbi.load("AnchorLog"),
            artifact("AnchorLog")["bytecode"],
            registry.contract_address,
        )
        assert anchor_log.contract_address is not None
        deployment = Deployment(registry.contract_address, anchor_log.contract_address)
        record = {**deployment.addresses(), "chain_id": self.chain_id, "admin": admin.address}
        atomic_write(data_dir / DEPLOYMENT_FILE, json.dumps(record).encode())
        log.info("deployed contracts", extra=record)
        return deployment

    def _apply_registration_mode(self, data_dir: Path, secret: str | None) -> None:
        """Switch the Registry to the configured mode when the operator's key is its admin.

        The keystore's address is read without its passphrase, so a ledger whose Registry is
        already in the configured mode never decrypts the admin key.
        """
        wanted = self.settings.registration_mode()
        addresses = ContractAddresses(self.deployment.registry, self.deployment.anchor_log)
        reader = Ledger(self.rpc, addresses)
        keystore = admin_keystore(data_dir)
        operator = Identity.keystore_address(keystore) if keystore.exists() else None
        current = reader.registration_mode()
        if not must_switch_mode(addresses.registry, current, wanted, reader.admin(), operator):
            return
        admin = Identity.load(keystore, passphrase(data_dir, secret).text)
        receipt = Ledger(self.rpc, addresses, admin).set_registration_mode(wanted)
        log.info(
            "registration mode set", extra={"mode": wanted.name.lower(), "tx": receipt.tx_hash}
        )

    # ----- JSON-RPC -----

    def forward(self, method: str, params: list[Any]) -> Any:
        """Relay a standard method to the node, its errors unchanged: the service's own
        transactions (role grants) go this way; ``/rpc`` relays with ``NodeForwarder``."""
        refusal = not_forwarded(method)
        if refusal is not None:
            raise refusal
        try:
            return self.rpc.request(method, params)
        except RpcError as exc:
            raise RpcFailure(exc.code, exc.message, exc.data) from exc

    # ----- index -----

    async def follow(self) -> None:
        """Poll the node for new events until cancelled; a failed round is retried, and a
        round that stopped short of the head is followed at once by the next."""
        reached = True
        while True:
            if reached:
                await anyio.sleep(self.settings.ledger_poll_interval_s)
            reached = await anyio.to_thread.run_sync(self.index_round)

    def index_round(self) -> bool:
        """``poll_once``, its failure logged for the next round to retry (True: wait before
        it). A node's malformed answer is logged as such, without a traceback: it is the
        node's fault, not a bug here, and what is wrong (the field and its value) is the
        whole story."""
        try:
            return self.poll_once()
        except InvalidAnswerError as exc:
            log.error(
                "indexing stopped at the node's malformed answer; the next round retries it",
                extra={"error": str(exc)},
            )
        except Exception:
            log.exception("indexing round failed; retrying")
        return True

    def poll_once(self) -> bool:
        """Index the confirmed blocks after the cursor, a bounded range per request and at
        most :data:`MAX_PAGES_PER_ROUND` ranges; True once the index reached the head.

        Each page is checked whole before any of it is stored: a log the node sends
        malformed, or outside the blocks and contracts asked for, is an
        ``InvalidAnswerError`` that leaves the cursor before its page. The page is asked
        again next round rather than skipped, since skipping would leave out of the index
        for good an event that an honest node (the same one fixed, or another) shows.
        """
        try:
            head = check_block(quantity(self.rpc.request("eth_blockNumber", [])))
        except ValueError as exc:
            raise InvalidAnswerError(f"the node's eth_blockNumber: {exc}") from None
        head -= self.settings.ledger_confirmations
        start = self._resume_point()
        page = self.settings.ledger_log_page_blocks
        addresses = [self.deployment.registry, self.deployment.anchor_log]
        asked = {bytes.fromhex(address[2:]) for address in addresses}
        pages = range(start, head + 1, page)
        for first in pages[:MAX_PAGES_PER_ROUND]:
            last = min(first + page - 1, head)
            query = {"address": addresses, "fromBlock": hex(first), "toBlock": hex(last)}
            answer = self.rpc.request("eth_getLogs", [query])
            if not isinstance(answer, list):
                raise InvalidAnswerError(
                    f"the node answered eth_getLogs with {shown_text(repr(answer))}, not a list"
                )
            logs = [LogEntry.from_rpc(raw) for raw in answer]
            for entry in logs:
                _check_asked(entry, first, last, asked)
            self.index.add_block(last, self._block_hash(last), logs)
        return len(pages) <= MAX_PAGES_PER_ROUND

    def _resume_point(self) -> int:
        cursor = self.index.cursor()
        if cursor is None:
            return self.settings.ledger_start_block
        number, indexed_hash = cursor
        if self._block_hash(number) == indexed_hash:
            return number + 1
        keep = max(number - REORG_DEPTH, self.settings.ledger_start_block)
        log.warning("chain reorganised; rewinding the index", extra={"to_block": keep})
        self.index.rewind(keep, self._block_hash(keep))
        return keep + 1

    def _block_hash(self, number: int) -> bytes:
        """The hash of block ``number``, which the cursor stores and compares."""
        block = self.rpc.request("eth_getBlockByNumber", [hex(number), False])
        try:
            return bytes.fromhex(check_hash(block["hash"])[2:])
        except (KeyError, TypeError, ValueError) as exc:
            raise InvalidAnswerError(
                f"the node's block {number}'s hash: {shown_text(str(exc))}"
            ) from None

    # ----- the rest of the Ledger interface -----

    def latest_block(self) -> dict[str, Any]:
        block = self.rpc.request("eth_getBlockByNumber", ["latest", False])
        return {
            "number": quantity(block["number"]),
            "hash": block["hash"],
            "parent_hash": block["parentHash"],
            "timestamp": quantity(block["timestamp"]),
            "transactions": block["transactions"],
            "chain_id": self.chain_id,
        }

    def fund(self, address: str) -> dict[str, Any]:
        raise FaucetUnavailable(
            "this ledger fronts an external chain and has no faucet; fund robots on that chain"
        )

    def close(self) -> None:
        self.index.close()
        self.rpc.close()


def _check_asked(entry: LogEntry, first: int, last: int, addresses: set[bytes]) -> None:
    """Refuse a log ``eth_getLogs`` was not asked for, as the SDK does (``Ledger._logs``):
    one of another block would be stored where the index was not looking, one of another
    contract was never the deployment's."""
    if not first <= entry.block_number <= last:
        raise InvalidAnswerError(
            f"the node answered eth_getLogs with a log of block {entry.block_number}, outside "
            f"the blocks {first} to {last} asked for"
        )
    if entry.address not in addresses:
        raise InvalidAnswerError(
            f"the node answered eth_getLogs with a log of address "
            f"{to_checksum_address(entry.address)}, not one asked for"
        )
