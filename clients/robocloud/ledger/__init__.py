"""The robot's view of the ledger: robocloud's contracts over standard Ethereum JSON-RPC.

``Ledger.connect(url, identity)`` finds the contracts through the ledger service; every
transaction is built from the ABIs shipped in this package and signed with the robot's key.
"""

from robocloud.ledger.abi import ContractAbi, decode_revert
from robocloud.ledger.client import ContractAddresses, Ledger, LedgerService
from robocloud.ledger.errors import (
    AddressError,
    ContractsUnavailableError,
    LedgerError,
    RevertError,
    RpcError,
    TransactionTimeoutError,
)
from robocloud.ledger.models import (
    Advertised,
    Advertisement,
    Anchor,
    IndexedAdvertisement,
    RegisteredRobot,
    RegistrationMode,
    Robot,
    Role,
)
from robocloud.ledger.rpc import JsonRpcClient
from robocloud.ledger.transactions import Receipt, SignedTransaction, Transactor

__all__ = [
    "AddressError",
    "Advertised",
    "Advertisement",
    "Anchor",
    "ContractAbi",
    "ContractAddresses",
    "ContractsUnavailableError",
    "IndexedAdvertisement",
    "JsonRpcClient",
    "Ledger",
    "LedgerError",
    "LedgerService",
    "Receipt",
    "RegisteredRobot",
    "RegistrationMode",
    "RevertError",
    "Robot",
    "Role",
    "RpcError",
    "SignedTransaction",
    "TransactionTimeoutError",
    "Transactor",
    "decode_revert",
]
