"""Two writers of one key in one process, as a storage node's anchorer and dataset publisher
are: each with its own ``Ledger`` (its own JSON-RPC client), sending at the same time."""

from __future__ import annotations

import contextlib
import threading
from typing import Any

from robocloud.identity import Identity
from robocloud.ledger import ContractAddresses, JsonRpcClient, Ledger
from tests.integration.robocloud.ledger.conftest import Deployment

METADATA = bytes.fromhex("01701220") + bytes(range(32))
DESCRIPTION = bytes.fromhex("01711220") + bytes(range(2, 34))


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
