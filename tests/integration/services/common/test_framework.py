"""Every service's framework, end to end against a real process: endpoints, errors, auth.

The storage service stands in for all five here (they share ``services.common``); a
separate test checks that each service starts and answers its framework endpoints.
"""

from __future__ import annotations

import hashlib
import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from robocloud.client import ServiceClient
from robocloud.config import SERVICES
from robocloud.errors import (
    AuthenticationError,
    MissingIdentityError,
    NotFoundError,
    PayloadTooLargeError,
    PermissionDeniedError,
    UnsupportedMediaTypeError,
)
from robocloud.identity import Identity
from robocloud.signing import EMPTY_SHA256, sign_request
from tests.conftest import ServiceFactory
from tests.integration.services.common.test_hostile_requests import serving_line
from tests.procs import REPO, ServiceProcess

BODY = b'{"challenge":"c-1"}'
LIMIT = 4096


@pytest.fixture(scope="module")
def storage(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One storage service for the module: each test signs with a fresh identity and nonce,
    and none changes what another reads."""
    data_dir = tmp_path_factory.mktemp("framework") / "storage"
    with ServiceProcess("storage", data_dir, {"ROBOCLOUD_MAX_BODY_BYTES": str(LIMIT)}) as process:
        yield process


@pytest.fixture
def http(storage: ServiceProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=storage.url, timeout=10) as client:
        yield client


AUDIENCE = "storage@local"


def signed_headers(
    identity: Identity,
    path: str = "/v1/whoami",
    body: bytes = BODY,
    audience: str = AUDIENCE,
    **kwargs: object,
) -> dict[str, str]:
    raw_path, _, query = path.partition("?")
    digest = hashlib.sha256(body).hexdigest() if body else EMPTY_SHA256
    headers = sign_request(identity.account, audience, "POST", raw_path, query, digest, **kwargs)  # type: ignore[arg-type]
    return {**headers, "Content-Type": "application/json"}


def assert_error(response: httpx.Response, status: int, code: str) -> dict[str, object]:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/json")
    error = response.json()["error"]
    assert error["code"] == code
    assert error["message"]
    assert error["request_id"] == response.headers["x-request-id"]
    return error


def test_framework_endpoints(http: httpx.Client) -> None:
    health = http.get("/healthz")
    assert health.json() == {"status": "ok", "service": "storage", "version": "0.1.0"}
    assert http.get("/readyz").json()["status"] == "ready"
    openapi = http.get("/openapi.json").json()
    assert openapi["info"]["title"] == "robocloud storage"
    assert "/v1/whoami" in openapi["paths"]
    assert 'src="/docs/assets/swagger-ui-bundle.js"' in http.get("/docs").text
    assert http.get("/docs/assets/swagger-ui-bundle.js").status_code == 200
    assert http.get("/v1/audience").json() == {
        "audience": "storage@local",
        "service": "storage",
        "deployment": "local",
    }
    metrics = http.get("/metrics")
    assert metrics.headers["content-type"].startswith("text/plain")
    assert 'robocloud_http_requests_total{method="GET",route="/healthz"' in metrics.text
    assert "robocloud_http_request_duration_seconds_bucket" in metrics.text


def test_signed_whoami_returns_the_verified_address(http: httpx.Client, identity: Identity) -> None:
    response = http.post("/v1/whoami", content=BODY, headers=signed_headers(identity))
    assert response.status_code == 200, response.text
    assert response.json() == {
        "address": identity.address,
        "service": "storage",
        "auth": "signed",
        "challenge": "c-1",
    }


def test_request_id_is_echoed_and_generated(http: httpx.Client) -> None:
    assert http.get("/healthz", headers={"X-Request-Id": "robot-req-0001"}).headers[
        "x-request-id"
    ] == ("robot-req-0001")
    generated = http.get("/healthz", headers={"X-Request-Id": "bad id!"}).headers["x-request-id"]
    assert len(generated) == 32


def test_changed_body_is_rejected_as_digest_mismatch(
    http: httpx.Client, identity: Identity
) -> None:
    headers = signed_headers(identity)
    response = http.post("/v1/whoami", content=b'{"challenge":"c-2"}', headers=headers)
    error = assert_error(response, 400, "body_digest_mismatch")
    assert error["details"]["header"] == "X-Robocloud-Content-SHA256"  # type: ignore[index]


@pytest.mark.parametrize(
    ("signed_path", "sent_path"),
    [("/v1/whoami", "/v1/whoami?x=1"), ("/v1/whoami?x=1", "/v1/whoami?x=2")],
    ids=["query-added", "query-changed"],
)
def test_changed_query_is_rejected(
    http: httpx.Client, identity: Identity, signed_path: str, sent_path: str
) -> None:
    response = http.post(sent_path, content=BODY, headers=signed_headers(identity, signed_path))
    assert_error(response, 401, "invalid_signature")


def test_a_repeated_key_sent_out_of_sorted_order_is_refused_before_the_route(
    http: httpx.Client, identity: Identity
) -> None:
    """The signature covers the values sorted and a route reads the last one sent, so a relay
    reordering ``?pin=false&pin=true`` would keep the signature and flip the meaning."""
    headers = signed_headers(identity, "/v1/whoami?x=1&x=2")
    error = assert_error(
        http.post("/v1/whoami?x=2&x=1", content=BODY, headers=headers), 401, "ambiguous_query"
    )
    assert "'x' repeats" in str(error["message"])
    assert http.post("/v1/whoami?x=1&x=2", content=BODY, headers=headers).status_code == 200


def test_changed_path_is_rejected(http: httpx.Client, identity: Identity) -> None:
    """The signature covers the path: one made for another path fails where a route takes it.
    A path no route takes is a 404 whatever the signature (nothing there to authorize)."""
    headers = signed_headers(identity, "/v1/other")
    assert_error(http.post("/v1/whoami", content=BODY, headers=headers), 401, "invalid_signature")
    headers = signed_headers(identity, "/v1/whoami")
    assert_error(http.post("/v1/other", content=BODY, headers=headers), 404, "not_found")


def test_stale_timestamp_is_rejected(http: httpx.Client, identity: Identity) -> None:
    headers = signed_headers(identity, timestamp=int(time.time()) - 400)
    error = assert_error(
        http.post("/v1/whoami", content=BODY, headers=headers), 401, "stale_timestamp"
    )
    assert error["details"] == {"header": "X-Robocloud-Timestamp"}


def test_replayed_nonce_is_rejected_even_after_a_restart(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    """On fl, whose restart takes a third of storage's: the nonce store is the framework's."""
    service = service_factory("fl")
    headers = signed_headers(identity, audience="fl@local")
    first = httpx.post(f"{service.url}/v1/whoami", content=BODY, headers=headers)
    assert first.status_code == 200
    replay = httpx.post(f"{service.url}/v1/whoami", content=BODY, headers=headers)
    assert_error(replay, 401, "replayed_nonce")
    service.restart()
    after = httpx.post(f"{service.url}/v1/whoami", content=BODY, headers=headers)
    assert_error(after, 401, "replayed_nonce")


@pytest.mark.parametrize(
    ("header", "value", "code"),
    [
        ("X-Robocloud-Signature", None, "missing_signature_header"),
        ("X-Robocloud-Signature", "0x" + "gg" * 65, "malformed_signature_header"),
        ("X-Robocloud-Address", "0xnothex", "malformed_signature_header"),
        ("X-Robocloud-Timestamp", "yesterday", "malformed_signature_header"),
        ("X-Robocloud-Nonce", "tiny", "malformed_signature_header"),
        ("X-Robocloud-Content-SHA256", None, "missing_signature_header"),
    ],
)
def test_malformed_or_missing_headers_are_401_naming_the_header(
    http: httpx.Client, identity: Identity, header: str, value: str | None, code: str
) -> None:
    headers = signed_headers(identity)
    if value is None:
        del headers[header]
    else:
        headers[header] = value
    error = assert_error(http.post("/v1/whoami", content=BODY, headers=headers), 401, code)
    assert error["details"] == {"header": header}


def test_unsigned_write_is_401(http: httpx.Client) -> None:
    assert_error(http.post("/v1/whoami", json={}), 401, "missing_signature_header")


def test_oversized_body_is_413_declared_or_streamed(http: httpx.Client, identity: Identity) -> None:
    big = json.dumps({"challenge": "x" * LIMIT}).encode()
    declared = http.post("/v1/whoami", content=big, headers=signed_headers(identity, body=big))
    assert_error(declared, 413, "payload_too_large")

    def chunks() -> Iterator[bytes]:
        yield big[:1000]
        yield big[1000:]

    streamed = http.post("/v1/whoami", content=chunks(), headers=signed_headers(identity, body=big))
    assert "content-length" not in streamed.request.headers
    assert_error(streamed, 413, "payload_too_large")


def test_unknown_route_is_404_in_the_error_model(http: httpx.Client) -> None:
    error = assert_error(http.get("/v1/nothing-here"), 404, "not_found")
    assert "/v1/nothing-here" in str(error["message"])


def test_wrong_content_type_is_415(http: httpx.Client, identity: Identity) -> None:
    headers = {**signed_headers(identity), "Content-Type": "text/plain"}
    error = assert_error(
        http.post("/v1/whoami", content=BODY, headers=headers), 415, "unsupported_media_type"
    )
    assert error["details"]["header"] == "Content-Type"  # type: ignore[index]


def test_invalid_field_names_its_path(http: httpx.Client, identity: Identity) -> None:
    body = b'{"challenge": 5}'
    response = http.post("/v1/whoami", content=body, headers=signed_headers(identity, body=body))
    error = assert_error(response, 422, "validation_error")
    assert error["details"]["errors"][0]["field"] == "body.challenge"  # type: ignore[index]


def test_sdk_client_signs_and_raises_typed_errors(
    storage: ServiceProcess, identity: Identity
) -> None:
    with ServiceClient(storage.url, identity) as client:
        assert client.post_json("/v1/whoami", {"challenge": "sdk"})["challenge"] == "sdk"
        with pytest.raises(NotFoundError) as missing:
            client.get_json("/v1/absent")
        assert missing.value.code == "not_found"
        assert missing.value.request_id
        with pytest.raises(UnsupportedMediaTypeError):
            client.request(
                "POST", "/v1/whoami", content=b"x", headers={"Content-Type": "text/plain"}
            )
        with pytest.raises(PayloadTooLargeError):
            client.post_json("/v1/whoami", {"challenge": "x" * LIMIT})
    with ServiceClient(storage.url) as anonymous:
        with pytest.raises(MissingIdentityError):
            anonymous.post_json("/v1/whoami", {})
        with pytest.raises(AuthenticationError):
            anonymous.request("POST", "/v1/whoami", signed=False, json={})


def test_sdk_client_retries_until_the_service_is_up(tmp_path: Path, identity: Identity) -> None:
    process = ServiceProcess("fl", tmp_path / "fl-late")
    late_start = threading.Timer(1.0, process.start)
    late_start.start()
    try:
        with ServiceClient(process.url, identity, retries=6, backoff_s=0.25) as client:
            assert client.post_json("/v1/whoami")["service"] == "fl"
    finally:
        late_start.join()
        process.stop()


def test_registered_mode_allows_only_listed_addresses(
    service_factory: ServiceFactory, identity: Identity
) -> None:
    allowed = Identity.generate()
    ledger = service_factory("ledger")
    service = service_factory(
        "broker",
        {
            "ROBOCLOUD_AUTH": "registered",
            "ROBOCLOUD_ALLOWED_ADDRESSES": allowed.address,
            "ROBOCLOUD_LEDGER_URL": ledger.url,
        },
    )
    with ServiceClient(service.url, allowed) as client:
        assert client.post_json("/v1/whoami")["auth"] == "registered"
    with (
        ServiceClient(service.url, identity) as client,
        pytest.raises(PermissionDeniedError) as denied,
    ):
        client.post_json("/v1/whoami")
    assert denied.value.details == {"address": identity.address}


@pytest.mark.parametrize("name", sorted(SERVICES))
def test_each_service_starts_and_answers_whoami(
    service_factory: ServiceFactory, identity: Identity, name: str
) -> None:
    service = service_factory(name)
    assert httpx.get(f"{service.url}/healthz").json()["service"] == name
    # py-evm needs its own limit for nested EVM calls; every other service runs with CPython's.
    assert serving_line(service)["recursion_limit"] == (12288 if name == "ledger" else 1000)
    deployment = "local" if name != "ledger" else service.audience.split("@")[1]
    assert service.audience == f"{name}@{deployment}"
    with ServiceClient(service.url, identity) as client:
        assert client.post_json("/v1/whoami") == {
            "address": identity.address,
            "service": name,
            "auth": "signed",
            "challenge": None,
        }


def test_a_service_that_cannot_start_exits_with_a_failure(tmp_path: Path) -> None:
    """On a port another socket holds, uvicorn cannot start: the process says so by its exit
    code (3, uvicorn's), so that a supervisor or a container restarts it or reports it, not
    0 as if it had been stopped. The runner serves through its own ``uvicorn.Server``, no
    longer ``uvicorn.run``, which checked that too."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        service = ServiceProcess("cas", tmp_path / "data", port=taken.getsockname()[1])
        process = subprocess.run(
            [sys.executable, "-m", "services.cas"],
            env=service.env,
            cwd=REPO,
            capture_output=True,
            timeout=60,
        )
    assert process.returncode == 3, process.stderr.decode()[-2000:]
    assert b"address already in use" in process.stderr.lower()
