"""`python -m services.ledger`: serve the ledger service with settings from the environment."""

import os

# Keccak is hashed some thirty times per mined transaction (trie nodes, RLP objects); eth-hash
# prefers pycryptodome (5 us a hash) when both backends are installed, pysha3 takes 0.7 us.
# Chosen before anything hashes: eth-hash fixes its backend at the first hash.
os.environ.setdefault("ETH_HASH_BACKEND", "pysha3")

from eth import EVM_RECURSION_LIMIT

from services.common.runner import run_service
from services.ledger.app import build_app
from services.ledger.settings import LedgerSettings

# py-evm recurses in Python once per nested EVM call (depth up to 1024). While calls run EVM
# code on worker threads, a transaction or a read waited some 5 ms for the GIL at each of its
# dozens of I/O steps (0.6-0.9 s a transaction under a flood of calls, 0.03-0.09 s at 0.5 ms).
run_service(
    "ledger",
    build_app,
    LedgerSettings,
    recursion_limit=EVM_RECURSION_LIMIT,
    switch_interval_s=0.0005,
)
