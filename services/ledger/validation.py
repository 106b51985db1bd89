"""The validity rules of EIP-155, EIP-2930, EIP-1559 and later forks that py-evm leaves to
the node, checked before a transaction is queued or mined, each refused with geth's message.

py-evm checks the signature (recovery, low ``s``), the fee cap against the base fee (with
its own message), the nonce and the balance while it executes; it does not check that the
priority fee is within the fee cap, that the gas covers the intrinsic cost and EIP-7623's
calldata floor, the block gas limit, EIP-7825's transaction gas cap, EIP-3860's init code
limit, the 256-bit bounds of the fee fields, EIP-2681's nonce bound, EIP-3607 (no
transactions from accounts with code other than an EIP-7702 delegation), nor the fields of
EIP-7702's authorizations.
Geth's transaction pool checks all of them with the messages below, which clients such as
ethers and viem classify by prefix (``intrinsic gas too low``, ``max fee per gas less than
block base fee``). Every rule raises before anything is queued, executed or stored.
"""

from __future__ import annotations

from dataclasses import dataclass

from eth.abc import SignedTransactionAPI
from eth.constants import CREATE_CONTRACT_ADDRESS
from eth.vm.forks.prague.constants import SET_CODE_TRANSACTION_TYPE
from eth_utils.crypto import keccak

from services.ledger.refusals import ChainError, InvalidParams

MAX_TRANSACTION_BYTES = 128 * 1024
"""geth's ``txMaxSize``: larger raw transactions are refused as ``oversized data``."""
MAX_INITCODE_BYTES = 2 * 24_576
"""EIP-3860: twice the EIP-170 code size limit."""
MAX_TRANSACTION_GAS = 2**24
"""EIP-7825 (Osaka; geth's ``MaxTxGas``): no transaction may carry more gas. py-evm runs
about 4.5 million gas a second of a JUMP loop and mines under the chain's lock, so this bounds
how long one transaction stalls every other write and state read (see docs/ledger.md)."""
UINT64_MAX = 2**64 - 1
UINT256_MAX = 2**256 - 1
TX_BASE_GAS = 21_000
FLOOR_GAS_PER_TOKEN = 10
"""EIP-7623 (Prague): the calldata floor, ``21000 + 10 * tokens``."""
DELEGATION_PREFIX = b"\xef\x01\x00"
"""EIP-7702: an account's code ``0xef0100 || address`` delegates its execution to address."""


def is_delegation(code: bytes) -> bool:
    return len(code) == 23 and code.startswith(DELEGATION_PREFIX)


@dataclass(frozen=True)
class Fees:
    """What a transaction offers per gas: its fee cap and its tip cap (both the gas price
    for legacy and EIP-2930 transactions, as in geth)."""

    cap: int
    tip: int

    @classmethod
    def of(cls, transaction: SignedTransactionAPI) -> Fees:
        if transaction.type_id in (None, 1):
            return cls(int(transaction.gas_price), int(transaction.gas_price))
        return cls(int(transaction.max_fee_per_gas), int(transaction.max_priority_fee_per_gas))


def check_raw_size(raw: bytes) -> None:
    if len(raw) > MAX_TRANSACTION_BYTES:
        raise ChainError(
            f"oversized data: transaction size {len(raw)}, limit {MAX_TRANSACTION_BYTES}"
        )


def check_fields(transaction: SignedTransactionAPI, chain_id: int, block_gas_limit: int) -> None:
    """The rules that need no state: bounds, replay protection, fees, gas."""
    if transaction.type_id == SET_CODE_TRANSACTION_TYPE:
        check_authorizations(transaction)
    if transaction.nonce > UINT64_MAX:
        raise InvalidParams("invalid raw transaction: nonce higher than 2^64-1")
    if transaction.gas > UINT64_MAX:
        raise InvalidParams("invalid raw transaction: gas higher than 2^64-1")
    if transaction.value > UINT256_MAX:
        raise InvalidParams("invalid raw transaction: value higher than 2^256-1")
    if transaction.chain_id is None:
        raise ChainError(
            "only replay-protected (EIP-155) transactions are accepted: sign with chain id "
            f"{chain_id}"
        )
    if transaction.chain_id != chain_id:
        raise ChainError(f"invalid chain id {transaction.chain_id}: this chain's id is {chain_id}")
    for entry in transaction.access_list:
        if len(entry[0]) != 20:
            raise InvalidParams(
                f"invalid raw transaction: access list address 0x{bytes(entry[0]).hex()} is not "
                "20 bytes"
            )
    creates = transaction.to == CREATE_CONTRACT_ADDRESS
    if creates and len(transaction.data) > MAX_INITCODE_BYTES:
        raise ChainError(
            f"max initcode size exceeded: code size {len(transaction.data)}, "
            f"limit {MAX_INITCODE_BYTES}"
        )
    if transaction.gas > block_gas_limit:
        raise ChainError("exceeds block gas limit")
    if transaction.gas > MAX_TRANSACTION_GAS:
        raise ChainError(
            f"transaction gas limit too high (cap: {MAX_TRANSACTION_GAS}, tx: {transaction.gas})"
        )
    fees = Fees.of(transaction)
    if fees.cap > UINT256_MAX:
        raise ChainError("max fee per gas higher than 2^256-1")
    if fees.tip > UINT256_MAX:
        raise ChainError("max priority fee per gas higher than 2^256-1")
    if fees.tip > fees.cap:
        raise ChainError("max priority fee per gas higher than max fee per gas")
    intrinsic = int(transaction.intrinsic_gas)
    if transaction.gas < intrinsic:
        raise ChainError(
            f"intrinsic gas too low: gas {transaction.gas}, minimum needed {intrinsic}"
        )
    floor = floor_data_gas(bytes(transaction.data))
    if transaction.gas < floor:
        raise ChainError(
            f"insufficient gas for floor data gas cost: gas {transaction.gas}, "
            f"minimum needed {floor}"
        )
    if transaction.nonce == UINT64_MAX:
        raise ChainError(
            f"nonce has max value: address 0x{transaction.sender.hex()}, nonce: {UINT64_MAX}"
        )


def check_authorizations(transaction: SignedTransactionAPI) -> None:
    """EIP-7702's set-code transaction as geth decodes it: a recipient (its ``to`` is an
    address, so it cannot create a contract), authorizations whose fields fit their types
    (anvil and geth cannot even decode one that does not: -32602, where py-evm let it reach
    the block and refused it there, -32000), and at least one authorization. An
    authorization with a wrong chain id, nonce or signature is valid here: it is skipped
    when the transaction executes, as the EIP says."""
    if transaction.to == CREATE_CONTRACT_ADDRESS:
        raise InvalidParams(
            "invalid raw transaction: EIP-7702 transaction cannot be used to create contract"
        )
    for position, auth in enumerate(transaction.authorization_list):
        bounds = (
            ("chain id", auth.chain_id, 256),
            ("nonce", auth.nonce, 64),
            ("y parity", auth.y_parity, 8),
            ("r", auth.r, 256),
            ("s", auth.s, 256),
        )
        for name, value, bits in bounds:
            if value >= 2**bits:
                raise InvalidParams(
                    f"invalid raw transaction: authorization {position}: {name} higher than "
                    f"2^{bits}-1"
                )
        if len(auth.address) != 20:
            raise InvalidParams(
                f"invalid raw transaction: authorization {position}: address "
                f"0x{bytes(auth.address).hex()} is not 20 bytes"
            )
    if not transaction.authorization_list:
        raise ChainError("EIP-7702 transaction with empty auth list")


def floor_data_gas(data: bytes) -> int:
    """EIP-7623's least gas for a transaction carrying ``data`` (a zero byte is one token,
    any other byte four)."""
    zeros = data.count(0)
    tokens = zeros + 4 * (len(data) - zeros)
    return TX_BASE_GAS + FLOOR_GAS_PER_TOKEN * tokens


def check_sender(transaction: SignedTransactionAPI, code: bytes, base_fee: int) -> None:
    """The rules that need the head's state: EIP-3607 and the base fee. A sender whose
    code is an EIP-7702 delegation designator is still an EOA (EIP-7702 amends EIP-3607 so):
    it holds its key and has delegated only what calls to it run."""
    if code and not is_delegation(code):
        raise ChainError(
            f"sender not an eoa: address 0x{transaction.sender.hex()}, "
            f"codehash: 0x{keccak(code).hex()}"
        )
    fees = Fees.of(transaction)
    if fees.cap < base_fee:
        raise ChainError(
            f"max fee per gas less than block base fee: address 0x{transaction.sender.hex()}, "
            f"maxFeePerGas: {fees.cap}, baseFee: {base_fee}"
        )


def max_cost(transaction: SignedTransactionAPI) -> int:
    """What the sender must hold: ``gas * fee cap + value``, as geth checks it."""
    return int(transaction.gas) * Fees.of(transaction).cap + int(transaction.value)
