"""The ledger operator's keys: the contracts' admin and the development faucet.

Both are generated at the first start and kept only as encrypted keystores (Web3 Secret
Storage, as robots keep theirs) under ``keys/`` in the data directory. The passphrase comes
from ``ROBOCLOUD_LEDGER_ADMIN_PASSPHRASE``; without it a random one is generated once into
``operator.secret`` (mode 0600) beside the keystores, so that a development chain needs no
configuration and no key ever sits on disk in the clear. The passphrase is never logged.

Two keys rather than one: the faucet sends transactions on its own schedule, and a separate
account keeps its nonces from racing the admin's (granting roles from a wallet or the SDK).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robocloud.identity import Identity
from services.common.keystores import KeyPassphrase, key_passphrase, service_key

SECRET_FILE = "operator.secret"
KEYS_DIR = "keys"
GENESIS_BALANCE_WEI = 10**9 * 10**18
"""What admin and faucet start with on the development chain: a billion ether each."""


@dataclass(frozen=True)
class OperatorKeys:
    admin: Identity
    faucet: Identity

    def genesis_state(self) -> dict[bytes, dict[str, Any]]:
        """py-evm genesis accounts: the admin and the faucet funded, nothing else."""
        return {
            bytes.fromhex(identity.address[2:]): {
                "balance": GENESIS_BALANCE_WEI,
                "nonce": 0,
                "code": b"",
                "storage": {},
            }
            for identity in (self.admin, self.faucet)
        }


def passphrase(data_dir: Path, configured: str | None) -> KeyPassphrase:
    """The configured passphrase, else the one generated into ``operator.secret``."""
    return key_passphrase(configured, data_dir / SECRET_FILE)


def admin_keystore(data_dir: Path) -> Path:
    """Where the admin's keystore lives (it may not exist yet)."""
    return data_dir / KEYS_DIR / "admin.json"


def load_or_create(data_dir: Path, secret: KeyPassphrase) -> OperatorKeys:
    """The operator's keys from their keystores, generated and saved on the first start."""
    keys = data_dir / KEYS_DIR
    keys.mkdir(parents=True, exist_ok=True)
    return OperatorKeys(
        admin=service_key(admin_keystore(data_dir), secret),
        faucet=service_key(keys / "faucet.json", secret),
    )
