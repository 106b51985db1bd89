"""Settings of the ledger service (``ROBOCLOUD_LEDGER_*``), beside those every service has."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, SecretStr

from robocloud.ledger.models import RegistrationMode
from services.common.settings import CommaList, ServiceSettings
from services.ledger.calls import CallLimits
from services.ledger.grants import RoleGrant, parse_grants
from services.ledger.pool import PoolLimits


class LedgerSettings(ServiceSettings):
    ledger_admin_passphrase: SecretStr | None = Field(
        default=None, description="encrypts the operator keystores; generated when unset"
    )
    ledger_rpc_url: str | None = Field(default=None, description="an external Ethereum node")
    ledger_registry_address: str | None = None
    ledger_anchor_log_address: str | None = None
    ledger_poll_interval_s: float = Field(default=1.0, gt=0)
    ledger_log_page_blocks: int = Field(default=2000, gt=0)
    ledger_confirmations: int = Field(default=0, ge=0)
    ledger_start_block: int = Field(default=0, ge=0)
    ledger_faucet_amount_wei: int = Field(default=10**18, gt=0)
    ledger_faucet_interval_s: float = Field(default=3600.0, ge=0)
    ledger_faucet_per_minute: int = Field(default=60, gt=0)
    ledger_rpc_gas_cap: int | None = Field(
        default=None, gt=0, description="gas an eth_call may use; unset: the block gas limit"
    )
    ledger_rpc_evm_timeout_s: float = Field(
        default=5.0, gt=0, description="wall-clock limit of one eth_call or eth_estimateGas"
    )
    ledger_rpc_max_calls: int = Field(
        default=2,
        gt=0,
        description="eth_call, eth_estimateGas, eth_createAccessList and eth_feeHistory "
        "executing at once; "
        "more wait up to the EVM timeout for a turn, then are refused (limit exceeded)",
    )
    ledger_rpc_batch_response_max_bytes: int = Field(
        default=25_000_000,
        gt=0,
        description="a batch whose answers pass this many bytes answers the calls left "
        "'response too large' (-32003) without running them (geth's "
        "--rpc.batch-response-max-size)",
    )
    ledger_rpc_max_forwards: int = Field(
        default=64,
        gt=0,
        description="external-node mode: requests relayed to the node at once (its "
        "connections); more wait up to 5 s, then are refused (limit exceeded)",
    )
    ledger_max_filters: int = Field(
        default=1000, gt=0, description="filters (eth_newFilter, eth_newBlockFilter) at once"
    )
    ledger_max_filters_per_client: int = Field(
        default=64,
        gt=0,
        description="of those, installed from one client address (an IPv4 address, an IPv6 "
        "/64) at once",
    )
    ledger_filter_timeout_s: float = Field(
        default=300.0, gt=0, description="a filter nobody polls for this long is removed"
    )
    ledger_pool_max_per_sender: int = Field(
        default=64, gt=0, description="transactions one sender may have waiting for a nonce gap"
    )
    ledger_pool_max_total: int = Field(
        default=1024, gt=0, description="transactions waiting for a nonce gap, all senders"
    )
    ledger_pool_timeout_s: float = Field(
        default=3 * 3600.0, gt=0, description="a transaction waits this long, then is dropped"
    )
    ledger_registration_mode: Literal["open", "approved"] = Field(
        default="open",
        description="open: robots register themselves; approved: a registrar approves each",
    )
    ledger_grant_roles: CommaList | None = Field(
        default=None,
        description="ROLE:ADDRESS or ROLE:URL (a storage node's /v1/node) granted at start; "
        "unset: storage_node:<ROBOCLOUD_STORAGE_URL>; empty: none",
    )

    def role_grants(self) -> list[RoleGrant]:
        entries = self.ledger_grant_roles
        if entries is None:
            entries = [f"storage_node:{self.storage_url}"]
        return parse_grants(entries)

    def admin_passphrase(self) -> str | None:
        secret = self.ledger_admin_passphrase
        return secret.get_secret_value() if secret is not None else None

    def call_limits(self) -> CallLimits:
        return CallLimits(self.ledger_rpc_gas_cap, self.ledger_rpc_evm_timeout_s)

    def pool_limits(self) -> PoolLimits:
        return PoolLimits(
            self.ledger_pool_max_per_sender, self.ledger_pool_max_total, self.ledger_pool_timeout_s
        )

    def registration_mode(self) -> RegistrationMode:
        return RegistrationMode[self.ledger_registration_mode.upper()]
