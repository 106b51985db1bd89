"""Settings of the storage service (``ROBOCLOUD_STORAGE_*``), beside those every service has.

Each engineer's settings sit in their own block, so that additions merge without conflicts.
"""

from __future__ import annotations

from pydantic import Field, SecretStr

from services.common.settings import ServiceSettings


class StorageSettings(ServiceSettings):
    # ----- record log, epochs and anchoring (engineer anchor) -----
    storage_epoch_s: float = Field(
        default=2.0, gt=0, le=2.0, description="the longest an epoch lasts (at most 2 s)"
    )
    storage_epoch_records: int = Field(
        default=10_000, gt=0, description="an epoch ends early once this many records arrived"
    )
    storage_anchor: bool = Field(
        default=True, description="anchor each epoch's TMT root through AnchorLog"
    )
    storage_anchor_retry_s: float = Field(
        default=1.0, gt=0, description="wait before retrying a failed anchor (doubles to 30 s)"
    )
    storage_node_passphrase: SecretStr | None = Field(
        default=None, description="encrypts the node's keystore; generated when unset"
    )
    storage_register: bool = Field(
        default=True,
        description="register the node's key on the Registry at start (faucet on a dev chain)",
    )

    def node_passphrase(self) -> str | None:
        secret = self.storage_node_passphrase
        return secret.get_secret_value() if secret is not None else None
