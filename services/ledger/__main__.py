"""`python -m services.ledger`: serve the ledger service with settings from the environment."""

from eth import EVM_RECURSION_LIMIT

from services.common.runner import run_service
from services.ledger.app import build_app
from services.ledger.settings import LedgerSettings

# py-evm recurses in Python once per nested EVM call (depth up to 1024).
run_service("ledger", build_app, LedgerSettings, recursion_limit=EVM_RECURSION_LIMIT)
