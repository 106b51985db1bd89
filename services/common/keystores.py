"""A service's own key, generated at its first start and kept only as an encrypted keystore.

The ledger's operator keys and a storage node's key live this way: Web3 Secret Storage under
the data directory, the passphrase from the service's settings or a generated secret file
(:func:`services.common.durable.generated_secret`), so that no key sits on disk in the clear.
"""

from __future__ import annotations

from pathlib import Path

from robocloud.errors import KeystoreError
from robocloud.identity import Identity
from services.common.durable import fsync_dir


def service_key(path: Path, passphrase: str) -> Identity:
    """The key in the keystore at ``path``, generated and made durable when there is none.

    Two processes starting on one data directory both find no keystore and both generate a
    key; the second's save finds the first's keystore in place (it never overwrites one), and
    it then reads that key, so both run with the same address.
    """
    if not path.exists():
        identity = Identity.generate()
        try:
            identity.save(path, passphrase)
        except KeystoreError:
            if not path.exists():
                raise
        else:
            fsync_dir(path.parent)
            return identity
    return Identity.load(path, passphrase)
