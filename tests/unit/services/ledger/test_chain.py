"""The embedded chain: contracts deployed once, refusals with node-style messages, durable
blocks that survive a reopen and a kill -9 with the same head hash."""

from __future__ import annotations

import itertools
import statistics
import textwrap
import time
from pathlib import Path

import pytest
from eth_account import Account
from eth_utils.crypto import keccak

from robocloud.identity import Identity
from robocloud.ledger.abi import ContractAbi
from services.ledger import chain as chain_module
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
from tests.unit.services.ledger.crash import (
    FailingDiskChild,
    acknowledged_before_kill,
    copy_as_killed,
    failing_fsync_library,
)

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
    mined = chain.send_raw_transaction(
        raw_call(robot, 0, deployment.registry, REGISTRY.encode_call("register", METADATA))
    ).mined
    assert mined is not None
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


FAILING_DISK = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from services.ledger.chain import CallRequest, EmbeddedChain
    from tests.unit.services.ledger.test_chain import keys
    operator = keys()
    chain = EmbeddedChain(Path(sys.argv[1]), operator.genesis_state())
    faucet = bytes.fromhex(operator.faucet.address[2:])
    chain.call(CallRequest(sender=faucet, to=faucet), "latest")  # a reader opens the store too
    print("ready", flush=True)
    for line in sys.stdin:
        try:
            mined = chain.send_raw_transaction(bytes.fromhex(line)).mined
        except Exception as exc:
            print("failed", type(exc).__name__, flush=True)
        else:
            print("mined", mined.block.number, flush=True)
    """
)


class FailingDiskChain(FailingDiskChild):
    """The chain in a child process with a failing disk; each transaction written to it is
    answered with a line."""

    def __init__(self, path: Path, library: Path, trigger: Path, persistent: bool) -> None:
        super().__init__(FAILING_DISK, path, library, trigger, persistent)

    def send(self, raw: bytes) -> str:
        return self.ask(raw.hex())


def transfer_from(operator: OperatorKeys, nonce: int) -> bytes:
    return raw_call(operator.faucet, nonce, "0x" + "22" * 20, b"", gas=21_000)


@pytest.mark.parametrize("persistent", [False, True], ids=["one-failure", "failing-until-answered"])
def test_a_commit_whose_fsync_failed_is_answered_as_a_restart_finds_it(
    tmp_path: Path, persistent: bool
) -> None:
    """A COMMIT whose fsync of the write-ahead log failed was answered as failed, yet its
    frames, commit marker included, stayed in the log: a restart before the next commit
    recovered the block, and the chain held a transaction its sender was told had failed
    (and was refused with "nonce too low" when it sent it again). The store as a kill -9
    right after that answer leaves it must lack the block, whether the disk failed once or
    until then, and the same process must mine the transaction sent again."""
    library = failing_fsync_library(tmp_path)
    trigger, path = tmp_path / "fail", tmp_path / "chain.sqlite"
    operator = keys()
    child = FailingDiskChain(path, library, trigger, persistent)
    try:
        assert child.send(transfer_from(operator, 0)) == "mined 1"
        trigger.touch()
        answer = child.send(transfer_from(operator, 1))
        assert trigger.exists() == persistent  # the fault happened
        trigger.unlink(missing_ok=True)
        crashed = copy_as_killed(path, tmp_path / "crashed")
        assert answer == "failed OperationalError"
        assert child.send(transfer_from(operator, 1)) == "mined 2"  # its robot sends it again
    finally:
        child.kill()
    faucet = bytes.fromhex(operator.faucet.address[2:])
    failed = keccak(transfer_from(operator, 1))
    after_crash = EmbeddedChain(crashed, operator.genesis_state())
    assert after_crash.head().block_number == 1
    assert after_crash.locate(failed) is None
    assert after_crash.nonce(faucet, "latest") == 1
    after_crash.close()
    after_kill = EmbeddedChain(path, operator.genesis_state())
    assert after_kill.head().block_number == 2
    assert after_kill.locate(failed) is not None
    assert after_kill.nonce(faucet, "latest") == 2
    after_kill.close()


def queue_behind_a_gap(chain: EmbeddedChain, robot: Identity, waiting: int) -> bytes:
    """Deploy the endless loop, queue ``waiting`` calls of 2,000,000 gas to it behind a nonce gap,
    and return the raw transaction that closes the gap (itself such a call)."""
    created = send_as(chain, robot, None, bytes.fromhex(DEPLOY_LOOP), gas=100_000)
    assert chain.locate(created) is not None
    loop = create_address(robot.address, 0)
    for nonce in range(2, 2 + waiting):
        queued = chain.send_raw_transaction(raw_call(robot, nonce, loop, b"", gas=2_000_000))
        assert queued.mined is None
    return raw_call(robot, 1, loop, b"", gas=2_000_000)


def test_the_gap_closer_is_answered_in_time_and_reads_go_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The transaction closing a nonce gap used to mine every waiting one after it before it
    was answered, in one turn of the chain's lock: 64 of 2^24 gas held its sender's answer
    and every read about four minutes. Now the answer waits ``PROMOTION_IN_ANSWER_S`` at
    most (none here), the waiting ones are mined after it, one block a turn, and each read
    goes first: between two reads, one block is mined. A reader the scheduler leaves out for
    a while (a busy machine) sees two now and then, so the typical step is what counts;
    all the blocks in one turn, or two a turn, make every step larger."""
    monkeypatch.setattr(chain_module, "PROMOTION_IN_ANSWER_S", 0.0)
    operator, robot = keys(), Identity.generate()
    chain = EmbeddedChain(tmp_path / "chain.sqlite", operator.genesis_state())
    fund(chain, operator, robot)
    waiting = 6
    closer = queue_behind_a_gap(chain, robot, waiting)
    first_block = chain.head().block_number + 1
    submitted = chain.send_raw_transaction(closer)
    assert submitted.mined is not None
    assert submitted.mined.block.number == first_block
    address = bytes.fromhex(robot.address[2:])
    assert chain.nonce(address, "latest") < 2 + waiting, "the answer waited for the rest"
    last = first_block + waiting
    seen = [chain.head().block_number]
    deadline = time.monotonic() + 120
    while seen[-1] < last:
        assert time.monotonic() < deadline, "the waiting transactions were not all mined"
        chain.balance(address, "latest")
        seen.append(chain.head().block_number)
    steps = [after - before for before, after in itertools.pairwise(seen) if after > before]
    assert statistics.median(steps) <= 1, f"reads did not go on between the blocks: {steps}"
    assert chain.nonce(address, "latest") == 2 + waiting
    chain.close()


def test_closing_stops_mining_waiting_transactions_after_one_block(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(chain_module, "PROMOTION_IN_ANSWER_S", 0.0)
    operator, robot = keys(), Identity.generate()
    path = tmp_path / "chain.sqlite"
    chain = EmbeddedChain(path, operator.genesis_state())
    fund(chain, operator, robot)
    waiting = 6
    closer = queue_behind_a_gap(chain, robot, waiting)
    first_block = chain.head().block_number + 1
    chain.send_raw_transaction(closer)
    started = time.monotonic()
    chain.close()
    assert time.monotonic() - started < 30, "closing waited for every waiting transaction"
    reopened = EmbeddedChain(path, operator.genesis_state())
    head = reopened.head().block_number
    assert first_block <= head < first_block + waiting
    nonce = reopened.nonce(bytes.fromhex(robot.address[2:]), "latest")
    assert nonce == 2 + head - first_block, "the head's nonce is the last mined block's"
    reopened.close()


def test_a_few_waiting_transfers_are_mined_before_the_answer(tmp_path: Path) -> None:
    """Within ``PROMOTION_IN_ANSWER_S`` the sender's answer comes after its waiting
    transactions: the quickest way to mine a few transfers, and their receipts are there
    when it asks."""
    operator, robot = keys(), Identity.generate()
    chain = EmbeddedChain(tmp_path / "chain.sqlite", operator.genesis_state())
    fund(chain, operator, robot)
    target = "0x" + "22" * 20
    for nonce in range(1, 4):
        assert chain.send_raw_transaction(raw_call(robot, nonce, target, b"")).mined is None
    submitted = chain.send_raw_transaction(raw_call(robot, 0, target, b""))
    assert submitted.mined is not None
    assert chain.nonce(bytes.fromhex(robot.address[2:]), "latest") == 4
    assert chain.head().block_number == submitted.mined.block.number + 3
    chain.close()
