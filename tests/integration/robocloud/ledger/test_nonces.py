"""Nonces: two writers of one key in one process, as a storage node's anchorer and dataset
publisher are, each with its own ``Ledger`` (its own JSON-RPC client), sending at the same time;
another process of the key taking the nonce first; and a transaction saved before it was sent,
resumed after a crash."""

from __future__ import annotations

import contextlib
import threading
from typing import Any

import pytest

from robocloud.identity import Identity
from robocloud.ledger import ContractAddresses, JsonRpcClient, Ledger, RpcError, SignedTransaction
from robocloud.ledger.transactions import NONCE_TAKEN, SIGNING_ATTEMPTS, Transactor, quantity
from tests.integration.robocloud.ledger.conftest import Deployment
from tests.integration.robocloud.ledger.nodes import robot_ledger
from tests.waiting import wait_for

METADATA = bytes.fromhex("01701220") + bytes(range(32))
DESCRIPTION = bytes.fromhex("01711220") + bytes(range(2, 34))
DEAD = "0x000000000000000000000000000000000000dEaD"


class MeetingAtTheNonce(JsonRpcClient):
    """Once it has read its pending nonce, a writer waits until the other writer has read its
    own (or a second passed): where two writers that do not share a nonce lock both read the
    same nonce, whatever the thread scheduling."""

    def __init__(self, url: str, meeting: threading.Barrier) -> None:
        super().__init__(url)
        self.meeting = meeting

    def request(self, method: str, params: list[Any] | None = None) -> Any:
        answer = super().request(method, params)
        if method == "eth_getTransactionCount" and params and params[-1] == "pending":
            with contextlib.suppress(threading.BrokenBarrierError):
                self.meeting.wait(timeout=1)
        return answer


def writer(
    url: str, addresses: ContractAddresses, identity: Identity, meeting: threading.Barrier
) -> Ledger:
    return Ledger(MeetingAtTheNonce(url, meeting), addresses, identity, receipt_timeout_s=10)


def test_two_writers_of_one_key_never_sign_the_same_nonce(deployment: Deployment) -> None:
    """Each read the pending nonce, signed and sent on its own: both signed the same nonce,
    and the node refused one of the two transactions ("nonce too low", "already known")."""
    identity = Identity.generate()
    deployment.fund(identity)
    meeting = threading.Barrier(2)
    anchorer = writer(deployment.url, deployment.addresses, identity, meeting)
    publisher = writer(deployment.url, deployment.addresses, identity, meeting)
    with anchorer, publisher:
        anchorer.register(METADATA)
        meeting.reset()
        cids = [bytes.fromhex("01551220") + bytes([n] * 32) for n in (1, 2)]
        errors: list[BaseException] = []

        def advertise(ledger: Ledger, cid: bytes) -> None:
            try:
                ledger.advertise(cid, DESCRIPTION)
            except BaseException as exc:
                errors.append(exc)

        threads = [
            threading.Thread(target=advertise, args=(ledger, cid))
            for ledger, cid in zip((anchorer, publisher), cids, strict=True)
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(30)
        assert errors == []
        advertised = anchorer.advertisements(advertiser=identity.address)
    assert sorted(event.cid for event in advertised) == cids


class AnotherProcessFirst(JsonRpcClient):
    """Each time the writer reads its pending nonce, another process of the key (outside
    this process's nonce lock) has just had a transfer on that nonce mined, ``left`` times
    more.

    Mined, not only sent: anvil's automine can leave a transaction unmined until the next one
    arrives when it follows its predecessor within milliseconds (foundry-rs/foundry #10122),
    as the writer's transaction follows the transfer; CI saw the writer's wait out its 10 s."""

    def __init__(self, url: str, identity: Identity) -> None:
        super().__init__(url)
        self.identity = identity
        self.left = 0
        self.sent: list[str] = []

    def request(self, method: str, params: list[Any] | None = None) -> Any:
        answer = super().request(method, params)
        pending_nonce = method == "eth_getTransactionCount" and params and params[-1] == "pending"
        if pending_nonce and self.left > 0:
            self.left -= 1
            self.sent.append(self._transfer(quantity(answer)))
        return answer

    def _transfer(self, nonce: int) -> str:
        signed = self.identity.account.sign_transaction(
            {
                "chainId": quantity(super().request("eth_chainId", [])),
                "nonce": nonce,
                "gas": 21_000,
                "gasPrice": quantity(super().request("eth_gasPrice", [])),
                "to": DEAD,
                "value": 1,
            }
        )
        tx_hash: str = super().request(
            "eth_sendRawTransaction", ["0x" + signed.raw_transaction.hex()]
        )
        wait_for(
            lambda: self._receipt(tx_hash), f"the other process's transfer {tx_hash} to be mined"
        )
        return tx_hash

    def _receipt(self, tx_hash: str) -> Any:
        return super().request("eth_getTransactionReceipt", [tx_hash])


def racing_ledger(deployment: Deployment) -> tuple[Ledger, AnotherProcessFirst]:
    """A registered robot's ``Ledger`` whose client lets another process win the nonce race
    as often as its ``left`` says."""
    identity = Identity.generate()
    deployment.fund(identity)
    rpc = AnotherProcessFirst(deployment.url, identity)
    ledger = Ledger(rpc, deployment.addresses, identity, receipt_timeout_s=10)
    ledger.register(METADATA)
    return ledger, rpc


def mined_count(deployment: Deployment, address: str) -> int:
    return quantity(deployment.rpc.request("eth_getTransactionCount", [address, "latest"]))


def test_a_nonce_another_process_took_is_signed_again(deployment: Deployment) -> None:
    """The node refuses the call's transaction ("nonce too low") twice; the call is signed
    on the next nonce each time and mined once, beside the other process's transfers."""
    ledger, other = racing_ledger(deployment)
    with ledger:
        start = mined_count(deployment, other.identity.address)
        other.left = 2
        cid = bytes.fromhex("01551220") + bytes([5] * 32)
        advertised = ledger.advertise(cid, DESCRIPTION)
        assert ledger.advertisements(cid=cid) == [advertised]
    receipts = [deployment.rpc.request("eth_getTransactionReceipt", [tx]) for tx in other.sent]
    assert [receipt["status"] for receipt in receipts] == ["0x1", "0x1"]
    assert mined_count(deployment, other.identity.address) == start + 3


def test_a_call_whose_nonce_is_taken_every_time_fails_after_its_attempts(
    deployment: Deployment,
) -> None:
    """Bounded: past ``SIGNING_ATTEMPTS`` refusals the node's refusal is the caller's, and
    nothing of the call is on chain."""
    ledger, other = racing_ledger(deployment)
    with ledger:
        start = mined_count(deployment, other.identity.address)
        other.left = SIGNING_ATTEMPTS
        cid = bytes.fromhex("01551220") + bytes([6] * 32)
        with pytest.raises(RpcError) as refused:
            ledger.advertise(cid, DESCRIPTION)
        assert refused.value.message.lower().startswith(NONCE_TAKEN)
        assert ledger.advertisements(cid=cid) == []
    assert len(other.sent) == SIGNING_ATTEMPTS
    assert mined_count(deployment, other.identity.address) == start + SIGNING_ATTEMPTS


def test_a_transfer_whose_nonce_was_taken_is_never_signed_again(deployment: Deployment) -> None:
    """Only the node says the nonce was taken; were it lying, it could mine every variant, and
    the robot would pay as often: a transaction moving ether is refused to the caller."""
    ledger, other = racing_ledger(deployment)
    with ledger:
        start = mined_count(deployment, other.identity.address)
        other.left = 1
        transactor = Transactor(other, other.identity)
        with pytest.raises(RpcError) as refused:
            transactor.send(DEAD, b"", value=2, gas=21_000)
    assert refused.value.message.lower().startswith(NONCE_TAKEN)
    assert (other.left, len(other.sent)) == (0, 1)
    assert mined_count(deployment, other.identity.address) == start + 1


class Crash(Exception):
    """The process dying between saving a signed transaction and sending it."""


def saved_unsent(ledger: Ledger, cid: bytes) -> SignedTransaction:
    """An advertise of ``cid`` signed and handed to ``before_send``, then never sent."""
    saved: list[SignedTransaction] = []

    def save_and_die(signed: SignedTransaction) -> None:
        saved.append(signed)
        raise Crash

    with pytest.raises(Crash):
        ledger.advertise(cid, DESCRIPTION, before_send=save_and_die)
    return saved[0]


def test_a_saved_transaction_is_resumed_with_the_same_bytes(deployment: Deployment) -> None:
    """Resumed, a saved transaction never sent is sent then (one advertisement, its hash the
    saved one's), and one already mined is only read back, not sent again."""
    identity = Identity.generate()
    deployment.fund(identity)
    with robot_ledger(deployment.url, deployment.addresses, identity) as ledger:
        ledger.register(METADATA)
        cid = bytes.fromhex("01551220") + bytes([3] * 32)
        signed = saved_unsent(ledger, cid)
        assert ledger.advertisements(cid=cid) == []
        first = ledger.advertised_by(signed, cid)
        again = ledger.advertised_by(signed, cid)
        assert ledger.advertisements(cid=cid) == [first] == [again]
    assert first is not None
    assert (first.tx_hash, first.description_cid) == (signed.tx_hash, DESCRIPTION)


def test_a_saved_transaction_whose_nonce_went_to_another_is_not_sent(
    deployment: Deployment,
) -> None:
    """Its nonce taken by a transaction mined since, it can never be mined: None, so that the
    caller signs a new one."""
    identity = Identity.generate()
    deployment.fund(identity)
    with robot_ledger(deployment.url, deployment.addresses, identity) as ledger:
        ledger.register(METADATA)
        cid = bytes.fromhex("01551220") + bytes([4] * 32)
        signed = saved_unsent(ledger, cid)
        ledger.update_metadata(METADATA)
        assert ledger.advertised_by(signed, cid) is None
        assert ledger.advertisements(cid=cid) == []
