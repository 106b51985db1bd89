"""The embedded chain: contracts deployed once, refusals with node-style messages, durable
blocks that survive a reopen and a kill -9 with the same head hash."""

from __future__ import annotations

import textwrap
import threading
import time
from pathlib import Path

import pytest
from eth_account import Account

from robocloud.identity import Identity
from robocloud.ledger.abi import ContractAbi
from services.ledger.chain import (
    CallRequest,
    ChainError,
    EmbeddedChain,
    InvalidParams,
    Reverted,
    receipt_status,
)
from services.ledger.contracts import create_address, deploy, send_as
from services.ledger.operator import OperatorKeys
from tests.unit.services.ledger.crash import acknowledged_before_kill

METADATA = bytes.fromhex("01551220") + bytes(32)
LOOP_RUNTIME = "5b600056"  # JUMPDEST PUSH1 0 JUMP: forever
DEPLOY_LOOP = "635b6000566000526004601cf3"  # return those 4 bytes as the contract's code
REGISTRY = ContractAbi.load("Registry")


def keys() -> OperatorKeys:
    return OperatorKeys(Identity.from_key(b"\x01" * 32), Identity.from_key(b"\x02" * 32))


def raw_call(
    identity: Identity, nonce: int, to: str, data: bytes, chain_id: int = 1337, gas: int = 300_000
) -> bytes:
    transaction = {"chainId": chain_id, "nonce": nonce, "gas": gas, "gasPrice": 2 * 10**9}
    transaction |= {"to": to, "data": data, "value": 0}
    return bytes(Account.sign_transaction(transaction, identity.account.key).raw_transaction)


def fund(chain: EmbeddedChain, operator: OperatorKeys, robot: Identity) -> None:
    send_as(chain, operator.faucet, robot.address, value=10**18)


def test_contracts_deploy_once_at_derived_addresses(tmp_path: Path) -> None:
    operator = keys()
    chain = EmbeddedChain(tmp_path / "chain.sqlite", operator.genesis_state())
    first = deploy(chain, operator.admin)
    assert first.registry == create_address(operator.admin.address, 0)
    head = chain.head().hash
    assert deploy(chain, operator.admin) == first
    assert chain.head().hash == head
    chain.close()


def test_reopen_keeps_head_hash_receipts_and_state(tmp_path: Path) -> None:
    operator, robot = keys(), Identity.generate()
    chain = EmbeddedChain(tmp_path / "chain.sqlite", operator.genesis_state())
    deployment = deploy(chain, operator.admin)
    fund(chain, operator, robot)
    (mined,) = chain.send_raw_transaction(
        raw_call(robot, 0, deployment.registry, REGISTRY.encode_call("register", METADATA))
    ).mined
    assert receipt_status(mined.receipts[0]) == 1
    head = chain.head()
    chain.close()

    reopened = EmbeddedChain(tmp_path / "chain.sqlite", keys().genesis_state())
    assert reopened.head() == head
    located = reopened.locate(mined.block.transactions[0].hash)
    assert located is not None
    assert located.block.hash == mined.block.hash
    call = CallRequest(
        sender=b"\x00" * 20,
        to=bytes.fromhex(deployment.registry[2:]),
        data=REGISTRY.encode_call("isActive", robot.address),
    )
    assert reopened.call(call, "latest")[-1] == 1
    reopened.close()


@pytest.fixture
def ready(tmp_path: Path) -> tuple[EmbeddedChain, str, Identity]:
    operator, robot = keys(), Identity.generate()
    chain = EmbeddedChain(tmp_path / "chain.sqlite", operator.genesis_state())
    deployment = deploy(chain, operator.admin)
    fund(chain, operator, robot)
    return chain, deployment.registry, robot


def test_malformed_raw_transaction(ready: tuple[EmbeddedChain, str, Identity]) -> None:
    chain, _, _ = ready
    head = chain.head()
    with pytest.raises(InvalidParams, match="invalid raw transaction"):
        chain.send_raw_transaction(b"\x12\x34")
    assert chain.head() == head


def test_wrong_chain_id(ready: tuple[EmbeddedChain, str, Identity]) -> None:
    chain, registry, robot = ready
    head = chain.head()
    data = REGISTRY.encode_call("register", METADATA)
    with pytest.raises(ChainError, match="invalid chain id 5"):
        chain.send_raw_transaction(raw_call(robot, 0, registry, data, chain_id=5))
    assert chain.head() == head


def test_nonce_too_low(ready: tuple[EmbeddedChain, str, Identity]) -> None:
    chain, registry, robot = ready
    chain.send_raw_transaction(raw_call(robot, 0, registry, REGISTRY.encode_call("register", b"x")))
    head = chain.head()
    with pytest.raises(ChainError, match="nonce too low"):
        chain.send_raw_transaction(raw_call(robot, 0, registry, b""))
    assert chain.head() == head


def test_insufficient_funds(ready: tuple[EmbeddedChain, str, Identity]) -> None:
    chain, registry, _ = ready
    poor = Identity.generate()
    head = chain.head()
    with pytest.raises(ChainError, match="insufficient funds"):
        chain.send_raw_transaction(raw_call(poor, 0, registry, b""))
    assert chain.head() == head


def test_call_revert_carries_reason_and_data(ready: tuple[EmbeddedChain, str, Identity]) -> None:
    chain, registry, robot = ready
    call = CallRequest(
        sender=bytes.fromhex(robot.address[2:]),
        to=bytes.fromhex(registry[2:]),
        data=REGISTRY.encode_call("advertise", b"\x01", b""),
    )
    with pytest.raises(Reverted) as raised:
        chain.estimate_gas(call, "latest")
    assert raised.value.message == "execution reverted: Registry: advertiser is not an active robot"
    assert raised.value.code == 3
    assert raised.value.data is not None
    assert raised.value.data.startswith("0x08c379a0")


SENDER = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from services.ledger.chain import EmbeddedChain
    from services.ledger.contracts import send_as
    from tests.unit.services.ledger.test_chain import keys
    operator = keys()
    chain = EmbeddedChain(Path(sys.argv[1]), operator.genesis_state())
    for n in range(1000):
        tx = send_as(chain, operator.faucet, "0x" + "22" * 20, value=n + 1)
        print(tx.hex(), chain.head().hash.hex(), flush=True)
    """
)


def test_kill_9_loses_no_acknowledged_transaction(tmp_path: Path) -> None:
    path = tmp_path / "chain.sqlite"
    acknowledged = [line.split() for line in acknowledged_before_kill(SENDER, path, 8)]
    chain = EmbeddedChain(path, keys().genesis_state())
    for tx_hash, _ in acknowledged:
        assert chain.locate(bytes.fromhex(tx_hash)) is not None
    assert chain.head().block_number >= len(acknowledged)
    assert chain.header_at(len(acknowledged)).hash.hex() == acknowledged[-1][1]
    chain.close()


def test_reads_go_on_between_the_blocks_of_waiting_transactions(tmp_path: Path) -> None:
    """The transaction closing a nonce gap used to mine every waiting one after it in one
    turn of the chain's lock: 64 of 2^24 gas held every read and the readiness check about
    four minutes. Now a read waits for one block at most, while the rest are still mined."""
    operator, robot = keys(), Identity.generate()
    chain = EmbeddedChain(tmp_path / "chain.sqlite", operator.genesis_state())
    fund(chain, operator, robot)
    created = send_as(chain, robot, None, bytes.fromhex(DEPLOY_LOOP), gas=100_000)
    located = chain.locate(created)
    assert located is not None
    loop = create_address(robot.address, 0)
    waiting = 6
    for nonce in range(2, 2 + waiting):
        queued = chain.send_raw_transaction(raw_call(robot, nonce, loop, b"", gas=2_000_000))
        assert queued.mined == ()
    first_block = chain.head().block_number + 1
    closing = threading.Thread(
        target=chain.send_raw_transaction,
        args=(raw_call(robot, 1, loop, b"", gas=2_000_000),),
    )
    closing.start()
    try:
        while chain.head().block_number < first_block:
            time.sleep(0.01)
        chain.balance(bytes.fromhex(robot.address[2:]), "latest")
        assert closing.is_alive(), "the read waited for every waiting transaction"
    finally:
        closing.join()
    assert chain.head().block_number == first_block + waiting
    assert chain.nonce(bytes.fromhex(robot.address[2:]), "latest") == 2 + waiting
    chain.close()
