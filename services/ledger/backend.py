"""The ledger's backend: the embedded development chain, or an external Ethereum node.

``ROBOCLOUD_LEDGER_RPC_URL`` decides. Both answer the routes' questions through the
``node.Ledger`` protocol, so nothing above this module knows which one runs.
"""

from __future__ import annotations

from services.ledger.external import ExternalLedger
from services.ledger.faucet import FaucetLimits
from services.ledger.filters import Filters
from services.ledger.node import EmbeddedLedger, Ledger
from services.ledger.settings import LedgerSettings


def open_ledger(settings: LedgerSettings) -> Ledger:
    """Open the backend ``settings`` name; slow (keys, deployment, catching up the index)."""
    data_dir = settings.resolved_data_dir()
    if settings.ledger_rpc_url:
        return ExternalLedger(settings, data_dir, settings.admin_passphrase())
    data_dir.mkdir(parents=True, exist_ok=True)
    limits = FaucetLimits(
        data_dir / "faucet.sqlite",
        settings.ledger_faucet_interval_s,
        settings.ledger_faucet_per_minute,
    )
    return EmbeddedLedger(
        data_dir,
        settings.admin_passphrase(),
        limits,
        settings.ledger_faucet_amount_wei,
        settings.call_limits(),
        settings.pool_limits(),
        settings.registration_mode(),
        Filters(
            settings.ledger_max_filters,
            settings.ledger_filter_timeout_s,
            max_per_client=settings.ledger_max_filters_per_client,
        ),
        settings.ledger_rpc_batch_response_max_bytes,
    )
