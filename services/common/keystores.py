"""A service's own key, generated at its first start and kept only as an encrypted keystore.

The ledger's operator keys and a storage node's key live this way: Web3 Secret Storage under
the data directory, the passphrase from the service's settings or a generated secret file
(:func:`services.common.durable.generated_secret`), so that no key sits on disk in the clear.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from robocloud.errors import KeystoreError
from robocloud.identity import STANDARD_SCRYPT_N, Identity
from services.common.durable import fsync_dir, generated_secret

GENERATED_SECRET_SCRYPT_N = 2**12
"""The scrypt cost of a keystore opened by a generated secret: geth's "light" setting."""


@dataclass(frozen=True)
class KeyPassphrase:
    """What opens a service's keystores, and the scrypt cost a new keystore gets."""

    text: str
    scrypt_n: int


def key_passphrase(configured: str | None, secret_file: Path) -> KeyPassphrase:
    """The configured passphrase at the standard cost, else the secret generated into
    ``secret_file`` at the light one.

    Stretching makes a passphrase a person chose costly to guess. A generated secret is 256
    random bits, out of reach of any guessing whatever its cost, so stretching it bought
    nothing and cost 1.2 s of a core at every open: each start of a storage node, two keys
    at the ledger's first start and the admin's again for role grants. At the light cost an
    open takes milliseconds.
    """
    if configured:
        return KeyPassphrase(configured, STANDARD_SCRYPT_N)
    return KeyPassphrase(generated_secret(secret_file), GENERATED_SECRET_SCRYPT_N)


def service_key(path: Path, passphrase: KeyPassphrase) -> Identity:
    """The key in the keystore at ``path``, generated and made durable when there is none.

    Two processes starting on one data directory both find no keystore and both generate a
    key; the second's save finds the first's keystore in place (it never overwrites one), and
    it then reads that key, so both run with the same address.
    """
    if not path.exists():
        identity = Identity.generate()
        try:
            identity.save(path, passphrase.text, scrypt_n=passphrase.scrypt_n)
        except KeystoreError:
            if not path.exists():
                raise
        else:
            fsync_dir(path.parent)
            return identity
    return Identity.load(path, passphrase.text)
