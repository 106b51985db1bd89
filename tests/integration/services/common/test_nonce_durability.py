"""A nonce the service acknowledged survives kill -9: its journal line was fsynced (on a
worker thread) before the request went on."""

from __future__ import annotations

import hashlib

import httpx

from robocloud.identity import Identity
from robocloud.signing import sign_request
from tests.conftest import ServiceFactory

BODY = b'{"challenge":"c-1"}'


def test_a_nonce_acknowledged_is_refused_after_kill_9(service_factory: ServiceFactory) -> None:
    storage = service_factory("storage")
    robot = Identity.generate()
    digest = hashlib.sha256(BODY).hexdigest()
    headers = {
        **sign_request(robot.account, storage.audience, "POST", "/v1/whoami", "", digest),
        "Content-Type": "application/json",
    }
    first = httpx.post(f"{storage.url}/v1/whoami", content=BODY, headers=headers)
    assert first.json()["address"] == robot.address
    storage.stop(kill=True)
    storage.start()
    replay = httpx.post(f"{storage.url}/v1/whoami", content=BODY, headers=headers)
    assert replay.status_code == 401
    assert replay.json()["error"]["code"] == "replayed_nonce"
