"""The ledger as the routes see it: a chain, its contracts, its event index and its faucet.

``EmbeddedLedger`` runs the development chain in-process; ``external.ExternalLedger`` fronts an
Ethereum node given by ``ROBOCLOUD_LEDGER_RPC_URL``. Both answer the same questions, so the
routes in ``app.py`` do not know which one they talk to.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Protocol

from robocloud.ledger.models import RegistrationMode
from services.ledger import encoding
from services.ledger.calls import CallLimits
from services.ledger.chain import ChainError, EmbeddedChain, MinedBlock
from services.ledger.contracts import Deployment, apply_registration_mode, deploy, send_as
from services.ledger.faucet import FaucetLimits
from services.ledger.filters import Filters
from services.ledger.index import EventIndex
from services.ledger.operator import OperatorKeys, load_or_create, passphrase
from services.ledger.pool import PoolLimits
from services.ledger.rpc import COSTLY_METHODS, Dispatcher, EmbeddedMethods

log = logging.getLogger("robocloud.ledger")


class FaucetUnavailable(Exception):
    """This ledger has no faucet (an external node: fund robots there)."""


class FaucetFailed(Exception):
    """The chain refused the faucet's transaction (its key out of funds): the grant was given
    back, so the robot may ask again."""


class Ledger(Protocol):
    chain_id: int
    deployment: Deployment
    index: EventIndex
    dispatcher: Dispatcher

    def latest_block(self) -> dict[str, Any]: ...

    def fund(self, address: str) -> dict[str, Any]: ...

    def close(self) -> None: ...


class EmbeddedLedger:
    """The development chain with its operator keys, contracts, index and faucet."""

    def __init__(
        self,
        data_dir: Path,
        configured_passphrase: str | None,
        limits: FaucetLimits,
        faucet_amount_wei: int,
        call_limits: CallLimits,
        pool_limits: PoolLimits,
        registration_mode: RegistrationMode,
        filters: Filters,
        batch_response_max_bytes: int,
    ) -> None:
        keys: OperatorKeys = load_or_create(data_dir, passphrase(data_dir, configured_passphrase))
        self.faucet_key = keys.faucet
        self.limits = limits
        self.faucet_amount_wei = faucet_amount_wei
        self.chain = EmbeddedChain(
            data_dir / "chain.sqlite", keys.genesis_state(), call_limits, pool_limits
        )
        self.chain_id = self.chain.chain_id
        self.deployment = deploy(self.chain, keys.admin)
        if apply_registration_mode(self.chain, keys.admin, self.deployment, registration_mode):
            log.info("registration mode set", extra={"mode": registration_mode.name.lower()})
        self.index = EventIndex(
            data_dir / "index.sqlite", self.deployment.registry, self.deployment.anchor_log
        )
        self.catch_up()
        self.chain.on_block(self._index_block)
        methods = EmbeddedMethods(self.chain, self.index, filters)
        self.dispatcher = Dispatcher(
            methods.table(),
            inline=methods.inline_table(),
            costly=COSTLY_METHODS,
            batch_timeout_s=call_limits.timeout_s,
            batch_response_max_bytes=batch_response_max_bytes,
        )
        log.info(
            "embedded chain ready",
            extra={
                "chain_id": self.chain_id,
                "head": self.chain.head().block_number,
                "admin": keys.admin.address,
                "faucet": keys.faucet.address,
                **self.deployment.addresses(),
            },
        )

    def catch_up(self, through: int | None = None) -> None:
        """Index every block after the index's cursor through ``through`` (the head when
        None): after a crash, on first start, or after an index write failed."""
        cursor = self.index.cursor()
        start = cursor[0] + 1 if cursor else 0
        last = self.chain.head().block_number if through is None else through
        for number in range(start, last + 1):
            block = self.chain.block_by_number(number)
            if block is None:
                break
            receipts = self.chain.receipts(block)
            self.index.add_block(number, block.hash, encoding.block_logs(block, receipts))

    def _index_block(self, mined: MinedBlock) -> None:
        """Index the block just mined, and first what an earlier failed write left out. It
        runs before the chain's head moves to the block, so catching up to the head alone
        stopped one block short, every time: the index stayed a block behind for good."""
        cursor = self.index.cursor()
        if cursor is not None and cursor[0] == mined.block.number - 1:
            logs = encoding.block_logs(mined.block, mined.receipts)
            self.index.add_block(mined.block.number, mined.block.hash, logs)
        else:
            self.catch_up(mined.block.number)

    def latest_block(self) -> dict[str, Any]:
        block = self.chain.block_by_number("latest")
        assert block is not None
        return {
            "number": block.number,
            "hash": encoding.data(block.hash),
            "parent_hash": encoding.data(block.header.parent_hash),
            "timestamp": block.header.timestamp,
            "transactions": [encoding.data(tx.hash) for tx in block.transactions],
            "chain_id": self.chain_id,
        }

    def fund(self, address: str) -> dict[str, Any]:
        """Send ``faucet_amount_wei`` to ``address`` in a real, mined transaction."""
        self.limits.acquire(address)
        try:
            tx_hash = send_as(self.chain, self.faucet_key, address, value=self.faucet_amount_wei)
        except ChainError as exc:
            self.limits.release(address)
            raise FaucetFailed(str(exc)) from exc
        except Exception:
            self.limits.release(address)  # a disk error: the robot may ask again at once
            raise
        located = self.chain.locate(tx_hash)
        return {
            "address": address,
            "amount_wei": str(self.faucet_amount_wei),
            "tx": encoding.data(tx_hash),
            "block": located.block.number if located else None,
        }

    def close(self) -> None:
        self.limits.close()
        self.index.close()
        self.chain.close()
