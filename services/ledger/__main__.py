"""`python -m services.ledger`: serve the ledger service with settings from the environment."""

from services.common.runner import run_service
from services.ledger.app import LedgerSettings, build_app

run_service("ledger", build_app, LedgerSettings)
