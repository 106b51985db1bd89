"""Who may write: signature verification state and the authorization policy.

Signatures are checked by the request guard (``middleware.py``) before the body is read;
this module holds what that check needs (the nonce store, the authorizer) and the
``SignedAddress`` dependency through which routes receive the verified signer.
"""

from __future__ import annotations

from typing import Annotated, Protocol

from fastapi import Depends, Request

from robocloud.signing import VerifiedRequest
from services.common.errors import Unauthorized
from services.common.settings import ServiceSettings


class Authorizer(Protocol):
    """Decides whether a verified signer may write, optionally in a given role."""

    async def authorize(self, address: str, role: str | None = None) -> None:
        """Return if allowed; raise :class:`Forbidden` naming the address otherwise."""
        ...

    async def holds_role(self, address: str, role: str) -> bool:
        """Whether ``address`` holds ``role`` (an operator's key holds every role), for what a
        role exempts its holder from rather than lets it do."""
        ...

    def close(self) -> None:
        """Release what the authorizer holds (connections to the ledger)."""
        ...


class AnySigner:
    """``ROBOCLOUD_AUTH=signed``: any valid signature may write (development, single service)."""

    async def authorize(self, address: str, role: str | None = None) -> None:
        return None

    async def holds_role(self, address: str, role: str) -> bool:
        """Nobody: without a ledger there are no roles."""
        return False

    def close(self) -> None:
        return None


def build_authorizer(settings: ServiceSettings) -> Authorizer:
    """The authorizer the settings ask for.

    ``registered`` asks the ledger at ``ROBOCLOUD_LEDGER_URL`` whether the signer is a
    registered, active robot; ``ROBOCLOUD_ALLOWED_ADDRESSES`` are let in regardless.
    """
    if settings.auth == "signed":
        return AnySigner()
    from services.common.registry_auth import RegistryAuthorizer

    return RegistryAuthorizer(settings.ledger_url, settings.allowed_addresses)


def verified_request(request: Request) -> VerifiedRequest:
    """The signature the guard verified for this request; 401 if the route was not signed."""
    verified = getattr(request.state, "signature", None)
    if not isinstance(verified, VerifiedRequest):
        raise Unauthorized("this route requires a signed request", code="signature_required")
    return verified


def signed_address(request: Request) -> str:
    return verified_request(request).address


SignedAddress = Annotated[str, Depends(signed_address)]
"""A route parameter of this type receives the checksummed address that signed the request."""


def require_role(role: str) -> object:
    """A dependency that also checks the signer holds ``role`` (for example ``storage``)."""

    async def dependency(request: Request) -> str:
        address = signed_address(request)
        await request.app.state.authorizer.authorize(address, role)
        return address

    return Depends(dependency)
