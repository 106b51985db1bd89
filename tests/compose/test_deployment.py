"""The Compose deployment from the host: health, signed writes, auth, durable volumes.

Every service shares ``services.common``, so the same checks run on all five through their
published ports; the nonce store is the state that must survive restarts and new containers.
"""

from __future__ import annotations

import hashlib
import json
import os

import httpx
import pytest

import robocloud
from robocloud.config import SERVICES
from robocloud.identity import Identity
from robocloud.signing import sign_request
from tests.compose.deployment import Deployment
from tests.procs import audience_of

pytestmark = pytest.mark.compose

BODY = json.dumps({"challenge": "compose"}).encode()


def signed_whoami(deployment: Deployment, service: str, headers: dict[str, str]) -> httpx.Response:
    return httpx.post(
        f"{deployment.urls[service]}/v1/whoami",
        content=BODY,
        headers={**headers, "Content-Type": "application/json"},
        timeout=10,
    )


def whoami_headers(deployment: Deployment, service: str, identity: Identity) -> dict[str, str]:
    return sign_request(
        identity.account,
        audience_of(deployment.urls[service]),
        "POST",
        "/v1/whoami",
        "",
        hashlib.sha256(BODY).hexdigest(),
    )


def assert_error(response: httpx.Response, status: int, code: str) -> None:
    assert response.status_code == status, response.text
    error = response.json()["error"]
    assert error["code"] == code
    assert error["request_id"] == response.headers["x-request-id"]


def test_every_service_is_healthy(deployment: Deployment) -> None:
    for service in SERVICES:
        health = httpx.get(f"{deployment.urls[service]}/healthz", timeout=5)
        assert health.json() == {
            "status": "ok",
            "service": service,
            "version": robocloud.__version__,
        }
        ready = httpx.get(f"{deployment.urls[service]}/readyz", timeout=5)
        assert ready.status_code == 200
        assert ready.json()["status"] == "ready"
        assert deployment.container(service)["State"]["Health"]["Status"] == "healthy"


def test_every_service_keeps_its_data_in_its_own_named_volume(deployment: Deployment) -> None:
    for service in SERVICES:
        mounts = deployment.container(service)["Mounts"]
        assert [(m["Type"], m["Name"], m["Destination"]) for m in mounts] == [
            ("volume", f"{deployment.project}_{service}-data", "/data")
        ]


def test_ports_are_published_on_loopback_only(deployment: Deployment) -> None:
    for service, port in SERVICES.items():
        bindings = deployment.container(service)["HostConfig"]["PortBindings"][f"{port}/tcp"]
        assert [binding["HostIp"] for binding in bindings] == ["127.0.0.1"]


PEER_PROBE = """
import json, os, urllib.request
names = ("CAS", "LEDGER", "STORAGE", "BROKER", "FL")
urls = {name: os.environ[f"ROBOCLOUD_{name}_URL"] for name in names}
print(json.dumps({
    name: [url, json.load(urllib.request.urlopen(f"{url}/healthz", timeout=5))["service"]]
    for name, url in urls.items()
}))
"""


def test_services_reach_their_peers_by_service_name(deployment: Deployment) -> None:
    """Peers are configured as http://<service>:<port> and resolve on the compose network."""
    expected = {
        service.upper(): [f"http://{service}:{port}", service] for service, port in SERVICES.items()
    }
    for service in SERVICES:
        answer = deployment.compose("exec", "-T", service, "python3", "-c", PEER_PROBE)
        assert json.loads(answer) == expected


def test_signed_whoami_answers_the_signer_on_every_service(deployment: Deployment) -> None:
    for service in SERVICES:
        with deployment.client(service) as client:
            answer = client.post_json("/v1/whoami", {"challenge": f"hello {service}"})
        assert answer["address"] == deployment.identity.address
        assert answer["service"] == service
        # The ledger lets any signer in (its faucet serves robots not yet registered).
        expected = (
            "signed" if service == "ledger" else os.environ.get("ROBOCLOUD_AUTH", "registered")
        )
        assert answer["auth"] == expected
        assert answer["challenge"] == f"hello {service}"


def test_unsigned_write_gets_401_on_every_service(deployment: Deployment) -> None:
    for service in SERVICES:
        response = httpx.post(
            f"{deployment.urls[service]}/v1/whoami",
            content=BODY,
            headers={"Content-Type": "application/json"},
            timeout=10,
        )
        assert_error(response, 401, "missing_signature_header")


def test_signer_outside_the_deployment_is_refused_in_registered_mode(
    deployment: Deployment,
) -> None:
    stranger = Identity.generate()
    for service in SERVICES:
        response = signed_whoami(deployment, service, whoami_headers(deployment, service, stranger))
        # The ledger lets any signer in: robots use its faucet before they can register.
        if os.environ.get("ROBOCLOUD_AUTH", "registered") == "registered" and service != "ledger":
            assert_error(response, 403, "address_not_allowed")
        else:
            assert response.json()["address"] == stranger.address


def test_used_nonces_survive_restart_and_new_containers(deployment: Deployment) -> None:
    used = {
        service: whoami_headers(deployment, service, deployment.identity) for service in SERVICES
    }
    for service, headers in used.items():
        assert signed_whoami(deployment, service, headers).status_code == 200
        assert_error(signed_whoami(deployment, service, headers), 401, "replayed_nonce")
    started = {service: deployment.container(service)["State"]["StartedAt"] for service in SERVICES}

    deployment.restart()
    for service, headers in used.items():
        assert deployment.container(service)["State"]["StartedAt"] != started[service]
        assert_error(signed_whoami(deployment, service, headers), 401, "replayed_nonce")
        fresh = signed_whoami(
            deployment, service, whoami_headers(deployment, service, deployment.identity)
        )
        assert fresh.json()["address"] == deployment.identity.address

    ids = {service: deployment.container(service)["Id"] for service in SERVICES}
    deployment.recreate()
    for service, headers in used.items():
        assert deployment.container(service)["Id"] != ids[service]
        assert_error(signed_whoami(deployment, service, headers), 401, "replayed_nonce")
