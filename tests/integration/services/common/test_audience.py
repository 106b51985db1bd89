"""Signatures bound to one service of one deployment, against real service processes.

A request a robot signed for cas is refused by the ledger, by another service and by cas of
another deployment (401 ``wrong_audience``), and the refusal changes nothing there: no
funds moved, no block stored, no nonce used.
"""

from __future__ import annotations

import hashlib
import json
import time
from typing import Any

import httpx
import pytest
from eth_account.messages import encode_defunct

from robocloud.client import ServiceClient
from robocloud.identity import Identity
from robocloud.signing import (
    HEADER_AUDIENCE,
    HEADER_SIGNATURE,
    SECP256K1_N,
    AudienceError,
    chain_deployment_id,
    sign_request,
)
from tests.conftest import ServiceFactory
from tests.integration.services.cas.conftest import multipart, repo_stat
from tests.procs import ServiceProcess, free_port

HELLO = b"Hello world"
HELLO_CID = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"
ADD = "/api/v0/add"


def signed_json(
    robot: Identity, audience: str, path: str, body: dict[str, Any]
) -> tuple[bytes, dict[str, str]]:
    content = json.dumps(body).encode()
    digest = hashlib.sha256(content).hexdigest()
    headers = sign_request(robot.account, audience, "POST", path, "", digest)
    return content, {**headers, "Content-Type": "application/json"}


def signed_add(robot: Identity, audience: str) -> tuple[bytes, dict[str, str]]:
    body, content_type = multipart(("hello.txt", HELLO))
    digest = hashlib.sha256(body).hexdigest()
    headers = sign_request(robot.account, audience, "POST", ADD, "cid-version=1", digest)
    return body, {**headers, "Content-Type": content_type}


def wrong_audience(response: httpx.Response, expected: str, received: str) -> None:
    assert response.status_code == 401, response.text
    error = response.json()["error"]
    assert error["code"] == "wrong_audience"
    assert error["details"] == {
        "header": HEADER_AUDIENCE,
        "expected": expected,
        "received": received,
    }
    assert expected in error["message"]


def balance(ledger: ServiceProcess, address: str) -> int:
    payload = {"jsonrpc": "2.0", "id": 1, "method": "eth_getBalance", "params": [address, "latest"]}
    return int(httpx.post(f"{ledger.url}/rpc", json=payload).json()["result"], 16)


def deployment_of(ledger: ServiceProcess) -> str:
    contracts = httpx.get(f"{ledger.url}/v1/contracts").json()
    registry = contracts["contracts"]["Registry"]["address"]
    return chain_deployment_id(contracts["chain_id"], registry)


def test_each_service_serves_its_audience_and_the_ledger_its_chain(
    service_factory: ServiceFactory,
) -> None:
    ledger = service_factory("ledger")
    deployment = deployment_of(ledger)
    assert deployment.startswith("1337:0x")
    assert httpx.get(f"{ledger.url}/v1/audience").json() == {
        "audience": f"ledger@{deployment}",
        "service": "ledger",
        "deployment": deployment,
    }
    cas = service_factory("cas")
    assert httpx.get(f"{cas.url}/v1/audience").json() == {
        "audience": "cas@local",
        "service": "cas",
        "deployment": "local",
    }


def test_faucet_request_signed_for_cas_moves_no_funds_on_the_ledger(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    ledger = service_factory("ledger")
    cas = service_factory("cas")
    own = ledger.audience
    other_deployment = "ledger@1337:0x" + "00" * 19 + "01"
    for audience in (cas.audience, other_deployment):
        body, headers = signed_json(identity, audience, "/v1/faucet", {"address": identity.address})
        response = httpx.post(f"{ledger.url}/v1/faucet", content=body, headers=headers)
        wrong_audience(response, own, audience)
        assert balance(ledger, identity.address) == 0
    body, headers = signed_json(identity, own, "/v1/faucet", {"address": identity.address})
    assert httpx.post(f"{ledger.url}/v1/faucet", content=body, headers=headers).status_code == 200
    assert balance(ledger, identity.address) > 0


def test_upload_signed_for_cas_is_refused_by_others_and_by_another_deployment(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    cas = service_factory("cas")
    other_deployment = service_factory("cas", {"ROBOCLOUD_DEPLOYMENT_ID": "staging"})
    storage = service_factory("storage")
    assert other_deployment.audience == "cas@staging"
    body, headers = signed_add(identity, cas.audience)
    response = httpx.post(
        f"{other_deployment.url}{ADD}?cid-version=1", content=body, headers=headers
    )
    wrong_audience(response, other_deployment.audience, "cas@local")
    # Storage has no such route: 404, before any signature is looked at.
    response = httpx.post(f"{storage.url}{ADD}?cid-version=1", content=body, headers=headers)
    assert (response.status_code, response.json()["error"]["code"]) == (404, "not_found")
    assert repo_stat(other_deployment.url)["NumObjects"] == 0
    assert httpx.get(f"{other_deployment.url}/ipfs/{HELLO_CID}").status_code == 404
    stored = httpx.post(f"{cas.url}{ADD}?cid-version=1", content=body, headers=headers)
    assert stored.json()["Hash"] == HELLO_CID, "the refusals elsewhere did not use the nonce"


def test_audience_header_rewritten_to_the_target_breaks_the_signature(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    cas = service_factory("cas")
    storage = service_factory("storage")
    body, headers = signed_json(identity, cas.audience, "/v1/whoami", {})
    headers[HEADER_AUDIENCE] = storage.audience
    response = httpx.post(f"{storage.url}/v1/whoami", content=body, headers=headers)
    assert response.status_code == 401
    assert response.json()["error"]["code"] == "invalid_signature"


def test_v1_signature_is_refused_naming_v2(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    storage = service_factory("storage")
    content = b"{}"
    digest = hashlib.sha256(content).hexdigest()
    v1_text = "\n".join(
        ["ROBOCLOUD-REQUEST-V1", "POST", "/v1/whoami", "", "1700000000", "n" * 16, digest]
    )
    signature = identity.account.sign_message(encode_defunct(text=v1_text)).signature
    headers = {
        "X-Robocloud-Address": identity.address,
        "X-Robocloud-Timestamp": "1700000000",
        "X-Robocloud-Nonce": "n" * 16,
        "X-Robocloud-Content-SHA256": digest,
        "X-Robocloud-Signature": "0x" + bytes(signature).hex(),
        "Content-Type": "application/json",
    }
    response = httpx.post(f"{storage.url}/v1/whoami", content=content, headers=headers)
    assert response.status_code == 401
    error = response.json()["error"]
    assert error["code"] == "unsupported_signature_version"
    assert "ROBOCLOUD-REQUEST-V2" in error["message"]
    assert error["details"] == {"header": HEADER_AUDIENCE}


def test_malleable_and_odd_v_twins_are_refused_and_use_no_nonce(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    storage = service_factory("storage")
    body, headers = signed_json(identity, storage.audience, "/v1/whoami", {"challenge": "x"})
    signature = bytes.fromhex(headers[HEADER_SIGNATURE][2:])
    s = int.from_bytes(signature[32:64], "big")
    high_s = signature[:32] + (SECP256K1_N - s).to_bytes(32, "big") + bytes([55 - signature[64]])
    odd_v = signature[:64] + bytes([signature[64] - 27])
    for twin in (high_s, odd_v):
        tampered = {**headers, HEADER_SIGNATURE: "0x" + twin.hex()}
        response = httpx.post(f"{storage.url}/v1/whoami", content=body, headers=tampered)
        assert response.status_code == 401, response.text
        assert response.json()["error"]["code"] == "non_canonical_signature"
    original = httpx.post(f"{storage.url}/v1/whoami", content=body, headers=headers)
    assert original.json()["address"] == identity.address


def test_sdk_fetches_the_audience_once_per_client(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    storage = service_factory("storage", {"ROBOCLOUD_AUDIENCE_NAME": "storage-eu"})
    with ServiceClient(storage.url, identity) as client:
        assert client.audience() == "storage-eu@local"
        for n in range(3):
            assert client.post_json("/v1/whoami", {"challenge": str(n)})["challenge"] == str(n)
    metrics = httpx.get(f"{storage.url}/metrics").text
    assert 'route="/v1/audience",service="storage",status="200"} 1.0' in metrics
    assert 'route="/v1/whoami",service="storage",status="200"} 3.0' in metrics


def test_sdk_signs_nothing_for_a_service_claiming_another_deployment(
    service_factory: ServiceFactory, identity: Identity, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A server of deployment B that claims A's audience (anyone can read it from A) would be
    handed signatures it could replay to A; a robot that names B refuses to sign for it."""
    impostor = service_factory("storage", {"ROBOCLOUD_DEPLOYMENT_ID": "deployment-a"})
    client = ServiceClient(impostor.url, identity, deployment="deployment-b")
    with client, pytest.raises(AudienceError, match="claims deployment 'deployment-a'"):
        client.post_json("/v1/whoami", {"challenge": "x"})
    monkeypatch.setenv("ROBOCLOUD_EXPECTED_DEPLOYMENT", "deployment-b")
    client = ServiceClient(impostor.url, identity)
    with client, pytest.raises(AudienceError, match="this robot expects 'deployment-b'"):
        client.post_json("/v1/whoami", {"challenge": "x"})
    assert "/v1/whoami" not in httpx.get(f"{impostor.url}/metrics").text
    monkeypatch.setenv("ROBOCLOUD_EXPECTED_DEPLOYMENT", "deployment-a")
    with ServiceClient(impostor.url, identity) as client:
        assert client.post_json("/v1/whoami", {"challenge": "x"})["address"] == identity.address


def test_replica_name_is_its_own_audience(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    replica = service_factory("storage", {"ROBOCLOUD_AUDIENCE_NAME": "storage-eu"})
    assert httpx.get(f"{replica.url}/v1/audience").json()["service"] == "storage-eu"
    body, headers = signed_json(identity, "storage@local", "/v1/whoami", {})
    response = httpx.post(f"{replica.url}/v1/whoami", content=body, headers=headers)
    wrong_audience(response, "storage-eu@local", "storage@local")


def test_registered_service_is_unready_until_it_learns_the_deployment_from_the_ledger(
    service_factory: ServiceFactory,
) -> None:
    robot = Identity.generate()
    ledger_port = free_port()
    broker = service_factory(
        "broker",
        {
            "ROBOCLOUD_AUTH": "registered",
            "ROBOCLOUD_LEDGER_URL": f"http://127.0.0.1:{ledger_port}",
            "ROBOCLOUD_ALLOWED_ADDRESSES": robot.address,
        },
        ready=False,
    )
    unready = httpx.get(f"{broker.url}/readyz")
    assert unready.status_code == 503
    checks = unready.json()["error"]["details"]["checks"]
    assert f"127.0.0.1:{ledger_port}" in checks["audience_known"]
    assert httpx.get(f"{broker.url}/v1/audience").json()["error"]["code"] == "audience_unknown"
    body, headers = signed_json(robot, "broker@local", "/v1/whoami", {})
    refused = httpx.post(f"{broker.url}/v1/whoami", content=body, headers=headers)
    assert refused.status_code == 503
    assert refused.json()["error"]["code"] == "audience_unknown"

    ledger = service_factory("ledger", port=ledger_port)
    broker.wait("/readyz")
    assert broker.audience == f"broker@{deployment_of(ledger)}"
    with ServiceClient(broker.url, robot) as client:
        assert client.post_json("/v1/whoami")["address"] == robot.address


def test_registered_service_pinned_to_another_deployment_stays_unready(
    service_factory: ServiceFactory,
) -> None:
    ledger = service_factory("ledger")
    pinned = "1337:0x" + "00" * 19 + "01"
    broker = service_factory(
        "broker",
        {
            "ROBOCLOUD_AUTH": "registered",
            "ROBOCLOUD_LEDGER_URL": ledger.url,
            "ROBOCLOUD_DEPLOYMENT_ID": pinned,
        },
        ready=False,
    )
    problem = ""
    deadline = time.monotonic() + 30
    while "ROBOCLOUD_DEPLOYMENT_ID" not in problem and time.monotonic() < deadline:
        unready = httpx.get(f"{broker.url}/readyz")
        assert unready.status_code == 503
        problem = unready.json()["error"]["details"]["checks"]["audience_known"]
        time.sleep(0.1)
    assert f"serves deployment {deployment_of(ledger)}" in problem
    assert f"ROBOCLOUD_DEPLOYMENT_ID is {pinned}" in problem
    assert httpx.get(f"{broker.url}/v1/audience").status_code == 503
