"""robocloud SDK: everything a robot runs to use the platform.

The pure modules (``signing``, ``identity`` and the wire formats) import nothing from the
services, so the services can share them: there is one implementation of each format.

``import robocloud`` is cheap (``__version__`` is read by every service's health route and by
``robocloud --version``): the names below are imported on first use (PEP 562), so httpx and
eth-account load only when a client or an identity is actually used.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from robocloud.client import ServiceClient
    from robocloud.errors import ApiError, RobocloudError, SignatureError, TransportError
    from robocloud.identity import Identity

__all__ = [
    "ApiError",
    "Identity",
    "RobocloudError",
    "ServiceClient",
    "SignatureError",
    "TransportError",
]
__version__ = "0.1.0"

_LAZY = {
    "ApiError": "robocloud.errors",
    "Identity": "robocloud.identity",
    "RobocloudError": "robocloud.errors",
    "ServiceClient": "robocloud.client",
    "SignatureError": "robocloud.errors",
    "TransportError": "robocloud.errors",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'robocloud' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])
