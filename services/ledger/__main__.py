"""`python -m services.ledger`: serve the ledger service with settings from the environment."""

import os

# Keccak is hashed some thirty times per mined transaction (trie nodes, RLP objects); eth-hash
# prefers pycryptodome (5 us a hash) when both backends are installed, pysha3 takes 0.7 us.
# Chosen before anything hashes: eth-hash fixes its backend at the first hash.
os.environ.setdefault("ETH_HASH_BACKEND", "pysha3")

from eth import EVM_RECURSION_LIMIT

from services.common.runner import BUSY_THREADS_SWITCH_INTERVAL_S, run_service
from services.ledger.app import build_app
from services.ledger.settings import LedgerSettings

# py-evm recurses in Python once per nested EVM call (depth up to 1024); calls run EVM code
# on worker threads for seconds.
run_service(
    "ledger",
    build_app,
    LedgerSettings,
    recursion_limit=EVM_RECURSION_LIMIT,
    switch_interval_s=BUSY_THREADS_SWITCH_INTERVAL_S,
)
