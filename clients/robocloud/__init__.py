"""robocloud SDK: everything a robot runs to use the platform.

The pure modules (``signing``, ``identity`` and the wire formats) import nothing from the
services, so the services can share them: there is one implementation of each format.
"""

from robocloud.client import ServiceClient
from robocloud.errors import ApiError, RobocloudError, SignatureError
from robocloud.identity import Identity

__all__ = ["ApiError", "Identity", "RobocloudError", "ServiceClient", "SignatureError"]
__version__ = "0.1.0"
