"""A robot's identity: an Ethereum key pair, kept at rest only as an encrypted keystore.

The keystore is the standard Web3 Secret Storage JSON (scrypt + AES-128-CTR) written by
eth-account, so keys move freely between robocloud and ordinary Ethereum wallets.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robocloud import bounded_json
from robocloud.bounded_json import JsonError
from robocloud.errors import KeystoreError
from robocloud.partial import written_whole

if TYPE_CHECKING:
    from eth_account import Account
    from eth_account.signers.local import LocalAccount

PASSPHRASE_ENV = "ROBOCLOUD_PASSPHRASE"
KEYSTORE_ENV = "ROBOCLOUD_KEYSTORE"
STANDARD_SCRYPT_N = 2**18
"""The scrypt cost of a keystore whose passphrase a person chose (geth's "standard")."""


def default_keystore_path() -> Path:
    """``$ROBOCLOUD_KEYSTORE``, else ``~/.robocloud/keystore.json``."""
    configured = os.environ.get(KEYSTORE_ENV)
    return Path(configured) if configured else Path.home() / ".robocloud" / "keystore.json"


class Identity:
    """A robot's signing key; its public identity is the checksummed address."""

    def __init__(self, account: LocalAccount) -> None:
        self.account = account

    @classmethod
    def generate(cls) -> Identity:
        return cls(_account().create())

    @classmethod
    def from_key(cls, private_key: bytes | str) -> Identity:
        return cls(_account().from_key(private_key))

    @property
    def address(self) -> str:
        return str(self.account.address)

    def did(self, chain_id: int) -> str:
        """The robot's DID as used in semantic descriptions (``did:pkh``)."""
        return f"did:pkh:eip155:{chain_id}:{self.address}"

    def save(self, path: Path, passphrase: str, *, scrypt_n: int = STANDARD_SCRYPT_N) -> None:
        """Write the encrypted keystore, readable by the owner only; never overwrite a key."""
        if not passphrase:
            raise KeystoreError("an empty passphrase would leave the key unprotected")
        keystore = _account().encrypt(
            self.account.key, passphrase, kdf="scrypt", iterations=scrypt_n
        )
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.exists() or path.is_symlink():
            raise KeystoreError(f"{path} already exists; refusing to overwrite a key")
        try:
            with written_whole(path, overwrite=False, mode=0o600) as handle:
                handle.write(json.dumps(keystore).encode())
                handle.flush()
                os.fsync(handle.fileno())
        except FileExistsError as exc:
            raise KeystoreError(f"{path} already exists; refusing to overwrite a key") from exc

    @classmethod
    def load(cls, path: Path, passphrase: str) -> Identity:
        try:
            keystore = _read_keystore(path)
        except FileNotFoundError as exc:
            hint = "create one with `robocloud keys new`"
            raise KeystoreError(f"no keystore at {path}; {hint}") from exc
        except (OSError, JsonError) as exc:
            raise KeystoreError(f"{path} is not a readable keystore: {exc}") from exc
        _check_kdf(path, keystore)
        try:
            key = _account().decrypt(keystore, passphrase)
        except (KeyError, TypeError) as exc:
            raise KeystoreError(f"{path} is not a valid keystore: missing {exc}") from exc
        except ValueError as exc:
            raise KeystoreError(f"cannot decrypt {path}: wrong passphrase") from exc
        return cls.from_key(key)

    @staticmethod
    def keystore_address(path: Path) -> str:
        """The address stored in a keystore, readable without the passphrase."""
        try:
            keystore = _read_keystore(path)
        except (OSError, JsonError) as exc:
            raise KeystoreError(f"{path} is not a readable keystore: {exc}") from exc
        address = keystore.get("address")
        if not isinstance(address, str):
            raise KeystoreError(f"{path} has no address field")
        from eth_utils.address import to_checksum_address  # on first use, as in _account

        try:
            return str(to_checksum_address("0x" + address.removeprefix("0x")))
        except ValueError as exc:
            raise KeystoreError(f"{path} has a malformed address: {address[:64]!r}") from exc


def _account() -> type[Account]:
    """eth-account's ``Account``, imported on first use: the import takes about a second
    (eth-keyfile loads py_ecc's BLS pairing tables), which every command paid before, even
    those that never touch a key (``get``, ``cat``, ``verify``, ``query``, ``--help``).

    py_ecc raises the interpreter's recursion limit to 100,000 as it loads; imported this
    late, inside a command that the CLI runs under CPython's 1,000 (``cli/main.py``), it left
    the rest of that command to overflow the C stack where it should raise
    ``RecursionError``. The limit the program had is put back.
    """
    limit = sys.getrecursionlimit()
    from eth_account import Account

    sys.setrecursionlimit(limit)
    return Account


def _read_keystore(path: Path) -> dict[str, Any]:
    """A keystore's JSON object; keystores travel between machines, so its nesting is bounded."""
    document = bounded_json.loads(path.read_bytes())
    if not isinstance(document, dict):
        raise JsonError("a keystore is a JSON object")
    return document


MAX_SCRYPT_MEMORY = 1 << 30
"""scrypt needs 128 * n * r bytes; robocloud writes 256 MiB keystores (n = 2**18, r = 8)."""
MAX_KDF_ROUNDS = 1 << 24


def _check_kdf(path: Path, keystore: dict[str, Any]) -> None:
    """Refuse key-derivation parameters that would take gigabytes or hours to try."""
    crypto = keystore.get("crypto") or keystore.get("Crypto")
    params = crypto.get("kdfparams") if isinstance(crypto, dict) else None
    if not isinstance(params, dict):
        return
    n, r, p, c = (params.get(name, 1) for name in ("n", "r", "p", "c"))
    if not all(isinstance(value, int) and value > 0 for value in (n, r, p, c)):
        raise KeystoreError(f"{path} has malformed key-derivation parameters")
    if 128 * n * r > MAX_SCRYPT_MEMORY or n * r * p > MAX_KDF_ROUNDS or c > MAX_KDF_ROUNDS:
        raise KeystoreError(f"{path} asks for key derivation beyond this SDK's bounds")
