"""Roles the ledger grants by itself at start: the storage node's, with no manual step.

``ROBOCLOUD_LEDGER_GRANT_ROLES`` lists ``role:target`` pairs. A target is an address, or the
URL of a storage node, whose address the ledger reads from its ``GET /v1/node``: the node
creates its key at its own first start, so nobody has to copy the address anywhere. Unset,
the list is ``storage_node:<ROBOCLOUD_STORAGE_URL>``: under ``make up`` and compose the storage
node gets its role as soon as it has registered. Empty, nothing is granted.

A grant is the operator's decision, made with the Registry's admin key, so it also approves
the target's registration when the Registry runs in the approved mode. The ledger retries
each grant until it is done (the node not yet up, not yet registered) for as long as it runs,
and grants nothing where its operator key is not the Registry's admin (an attached external
deployment): that operator grants with ``robocloud admin grant ADDRESS ROLE``. A URL target
is trusted as far as the network path to it is: name one the operator controls.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
from eth_utils.address import is_address, to_checksum_address

from robocloud import bounded_json
from robocloud.identity import Identity
from robocloud.ledger import ContractAddresses, JsonRpcClient, Ledger
from robocloud.ledger.models import Role
from services.ledger.operator import admin_keystore, passphrase

log = logging.getLogger("robocloud.ledger.grants")

NODE_ANSWER_BYTES = 64 * 1024
"""A storage node's ``/v1/node`` answer is a few hundred bytes; more is not one."""


class GrantSettingError(ValueError):
    """An entry of ``ROBOCLOUD_LEDGER_GRANT_ROLES`` that is not ``role:address`` or ``role:URL``."""


@dataclass(frozen=True)
class RoleGrant:
    role: Role
    target: str
    """A checksummed address, or an http(s) URL of a service publishing ``/v1/node``."""

    @classmethod
    def parse(cls, entry: str) -> RoleGrant:
        role_name, separator, target = entry.partition(":")
        roles = {role.value: role for role in Role}
        if not separator or role_name not in roles:
            raise GrantSettingError(
                f"ROBOCLOUD_LEDGER_GRANT_ROLES entry {entry!r}: expected ROLE:ADDRESS or "
                f"ROLE:URL with ROLE one of {', '.join(sorted(roles))}"
            )
        if is_address(target):
            return cls(roles[role_name], str(to_checksum_address(target)))
        if target.startswith(("http://", "https://")):
            return cls(roles[role_name], target.rstrip("/"))
        raise GrantSettingError(
            f"ROBOCLOUD_LEDGER_GRANT_ROLES entry {entry!r}: {target!r} is neither an address "
            "nor an http(s) URL"
        )


def parse_grants(entries: list[str]) -> list[RoleGrant]:
    return [RoleGrant.parse(entry) for entry in entries]


NODE_ANSWER_TIMEOUT_S = 5.0


def published_address(client: httpx.Client, url: str) -> str | None:
    """The address a service publishes at ``{url}/v1/node``; None while it does not answer."""
    try:
        with client.stream("GET", f"{url}/v1/node") as response:
            if response.status_code != 200:
                return None
            body = b""
            for chunk in response.iter_bytes():
                body += chunk
                if len(body) > NODE_ANSWER_BYTES:
                    return None
    except httpx.HTTPError:
        return None
    try:
        document: Any = bounded_json.loads(body, max_depth=8)
    except ValueError:
        return None
    address = document.get("address") if isinstance(document, dict) else None
    if not isinstance(address, str) or not is_address(address):
        return None
    return str(to_checksum_address(address))


class RoleGranter:
    """Applies the configured grants, one attempt at a time.

    ``reader`` reads the chain; ``writer`` gives a client signing with the admin's key, asked
    for only when a transaction is needed (decrypting a keystore costs a second of scrypt).
    URL targets are read with one HTTP client for the granter's life: a new client loads the
    CA bundle (18 ms), and a node that is down is asked every poll interval for as long as
    the ledger runs.
    """

    def __init__(
        self, reader: Ledger, writer: Callable[[], Ledger], grants: list[RoleGrant]
    ) -> None:
        self.reader = reader
        self.remaining = list(grants)
        self._writer = writer
        self._signing: Ledger | None = None
        self._http = httpx.Client(timeout=NODE_ANSWER_TIMEOUT_S)

    def close(self) -> None:
        self._http.close()
        self.reader.close()

    def attempt(self) -> bool:
        """Try every remaining grant once; whether all are done."""
        still: list[RoleGrant] = []
        for grant in self.remaining:
            if not self._apply(grant):
                still.append(grant)
        self.remaining = still
        return not still

    def _admin(self) -> Ledger:
        if self._signing is None:
            self._signing = self._writer()
        return self._signing

    def _apply(self, grant: RoleGrant) -> bool:
        address = (
            grant.target
            if grant.target.startswith("0x")
            else published_address(self._http, grant.target)
        )
        if address is None:
            return False
        if self.reader.has_role(address, grant.role, active=False):
            return True
        if self.reader.is_pending(address):
            self._admin().approve(address)
            log.info("registration approved", extra={"address": address})
        if not self.reader.robot(address).registered:
            return False
        receipt = self._admin().grant_role(address, grant.role)
        log.info(
            "role granted",
            extra={"address": address, "role": grant.role.value, "tx": receipt.tx_hash},
        )
        return True


class DispatcherTransport(httpx.BaseTransport):
    """JSON-RPC straight into the ledger's own dispatcher: the SDK without a network hop."""

    def __init__(self, handle: Callable[[bytes], Any]) -> None:
        self._handle = handle

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        answer = self._handle(request.read())
        if answer is None:
            return httpx.Response(204)
        return httpx.Response(200, json=answer)


def open_granter(
    dispatch: Callable[[bytes], Any],
    addresses: ContractAddresses,
    data_dir: Path,
    configured_passphrase: str | None,
    grants: list[RoleGrant],
) -> RoleGranter | None:
    """A granter signing with the operator's admin key; None where that key is not the admin.

    Transactions go through the ledger's own dispatcher, so the embedded chain and an
    external node are driven the same way.
    """
    keystore = admin_keystore(data_dir)
    if not keystore.exists():
        log.warning("no admin keystore: roles are not granted", extra={"path": str(keystore)})
        return None
    operator = Identity.keystore_address(keystore)
    rpc = JsonRpcClient("http://ledger.local/rpc", transport=DispatcherTransport(dispatch))
    reader = Ledger(rpc, addresses)
    if reader.admin().lower() != operator.lower():
        log.warning(
            "the operator key is not the Registry's admin: roles are not granted",
            extra={"operator": operator},
        )
        reader.close()
        return None

    def writer() -> Ledger:
        admin = Identity.load(keystore, passphrase(data_dir, configured_passphrase).text)
        return Ledger(rpc, addresses, admin)

    return RoleGranter(reader, writer, grants)
