"""Every bad input the issue names: a clear JSON error, and nothing stored or lost."""

from __future__ import annotations

import hashlib
import socket
import time

import httpx
import pytest

from robocloud.car import write_car
from robocloud.cas import Cas
from robocloud.cid import CID, Block
from robocloud.client import ServiceClient
from robocloud.errors import ApiError
from robocloud.identity import Identity
from robocloud.signing import sign_request
from robocloud.unixfs import ImportParams, import_bytes
from tests.conftest import ServiceFactory
from tests.integration.services.cas.conftest import (
    QUIET_GC,
    error_of,
    multipart,
    repo_stat,
    store_unchanged,
)
from tests.procs import ServiceProcess

UNKNOWN = CID.from_block(b"never stored anywhere")


def nothing_stored(service: ServiceProcess) -> None:
    assert repo_stat(service.url)["NumObjects"] == 0
    assert httpx.post(f"{service.url}/api/v0/pin/ls").json() == {"Keys": {}}
    assert list((service.data_dir / "packs").iterdir()) == []
    assert list((service.data_dir / "spool").iterdir()) == []


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("GET", "/ipfs/{cid}"),
        ("POST", "/api/v0/cat?arg={cid}"),
        ("POST", "/api/v0/block/get?arg={cid}"),
    ],
)
def test_invalid_cid_is_400(shared_cas_service: ServiceProcess, method: str, path: str) -> None:
    response = httpx.request(method, shared_cas_service.url + path.format(cid="bafyNOT-A-CID"))
    assert response.status_code == 400
    error = response.json()["error"]
    assert error["code"] == "invalid_cid"
    assert error["details"]["cid"] == "bafyNOT-A-CID"
    assert "bafyNOT-A-CID" in error["message"]


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("GET", "/ipfs/{cid}"),
        ("GET", "/ipfs/{cid}?format=raw"),
        ("GET", "/ipfs/{cid}?format=car"),
        ("POST", "/api/v0/cat?arg={cid}"),
        ("POST", "/api/v0/block/stat?arg={cid}"),
        ("POST", "/api/v0/dag/export?arg={cid}"),
    ],
)
def test_unknown_cid_is_404(shared_cas_service: ServiceProcess, method: str, path: str) -> None:
    response = httpx.request(method, shared_cas_service.url + path.format(cid=UNKNOWN))
    assert response.status_code == 404
    error = response.json()["error"]
    assert error["code"] == "block_not_found"
    assert error["details"] == {"cid": str(UNKNOWN)}


def test_pinning_an_unknown_cid_is_404_and_pins_nothing(
    cas: Cas, cas_service: ServiceProcess
) -> None:
    with pytest.raises(ApiError) as exc:
        cas.pin(UNKNOWN)
    assert error_of(exc, 404, "block_not_found").details["missing"] == str(UNKNOWN)
    assert cas.pins() == {}


def test_truncated_multipart_stores_nothing(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    body, content_type = multipart(("big", bytes(600_000)))
    truncated = body[: body.rindex(b"\r\n--")]
    with pytest.raises(ApiError) as exc:
        signed.request(
            "POST", "/api/v0/add", content=truncated, headers={"Content-Type": content_type}
        )
    assert "nothing was stored" in error_of(exc, 400, "truncated_multipart").message
    nothing_stored(cas_service)


def test_upload_cut_off_mid_body_stores_nothing(
    cas_service: ServiceProcess, identity: Identity
) -> None:
    body, content_type = multipart(("big", bytes(range(256)) * 4096))
    digest = hashlib.sha256(body).hexdigest()
    audience = cas_service.audience
    headers = sign_request(identity.account, audience, "POST", "/api/v0/add", "", digest)
    head = "".join(f"{name}: {value}\r\n" for name, value in headers.items())
    request = (
        f"POST /api/v0/add HTTP/1.1\r\nHost: 127.0.0.1\r\n{head}"
        f"Content-Type: {content_type}\r\nContent-Length: {len(body)}\r\n\r\n"
    ).encode()
    logged = cas_service.log().count('"path": "/api/v0/add"')
    with socket.create_connection(("127.0.0.1", cas_service.port)) as sock:
        sock.sendall(request + body[: len(body) // 2])
    deadline = time.monotonic() + 30
    while cas_service.log().count('"path": "/api/v0/add"') == logged:
        assert time.monotonic() < deadline, "the cut-off upload never ended on the service"
        time.sleep(0.05)
    nothing_stored(cas_service)
    log = cas_service.log()
    assert "unhandled error" not in log
    assert "Traceback" not in log
    [line] = [entry for entry in log.splitlines() if '"path": "/api/v0/add"' in entry]
    assert '"status": 499' in line
    assert '"level": "info"' in line


def test_body_not_matching_its_signed_digest_stores_nothing(
    cas_service: ServiceProcess, identity: Identity
) -> None:
    body, content_type = multipart(("f", b"what was signed"))
    tampered, _ = multipart(("f", b"what was sent!!"), boundary=content_type.split("=")[1])
    headers = sign_request(
        identity.account,
        cas_service.audience,
        "POST",
        "/api/v0/add",
        "",
        hashlib.sha256(body).hexdigest(),
    )
    response = httpx.post(
        f"{cas_service.url}/api/v0/add",
        content=tampered,
        headers={**headers, "Content-Type": content_type},
    )
    assert response.status_code == 400
    assert response.json()["error"]["code"] == "body_digest_mismatch"
    nothing_stored(cas_service)


def test_car_with_one_bad_block_is_rejected_whole(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    blocks, root = import_bytes(bytes(range(256)) * 2000, ImportParams(chunk_size=100_000))
    liar = Block(blocks[2].cid, b"not the bytes of this CID")
    car = b"".join(write_car([root], [*blocks[:2], liar, *blocks[3:]]))
    body, content_type = multipart(("evil.car", car))
    with pytest.raises(ApiError) as exc:
        signed.request(
            "POST", "/api/v0/dag/import", content=body, headers={"Content-Type": content_type}
        )
    error = error_of(exc, 400, "invalid_car")
    assert str(blocks[2].cid) in error.message
    assert "nothing was stored" in error.message
    nothing_stored(cas_service)


def test_garbage_car_is_400(signed: ServiceClient, cas_service: ServiceProcess) -> None:
    body, content_type = multipart(("x.car", b"\x05hello this is not a car"))
    with pytest.raises(ApiError) as exc:
        signed.request(
            "POST", "/api/v0/dag/import", content=body, headers={"Content-Type": content_type}
        )
    error_of(exc, 400, "invalid_car")
    nothing_stored(cas_service)


@pytest.fixture
def small_cas(service_factory: ServiceFactory) -> ServiceProcess:
    return service_factory("cas", {**QUIET_GC, "ROBOCLOUD_CAS_MAX_UPLOAD_BYTES": "100000"})


def test_oversized_upload_is_413(small_cas: ServiceProcess, identity: Identity) -> None:
    body, content_type = multipart(("big", bytes(200_000)))
    with ServiceClient(small_cas.url, identity, retries=0) as client:
        with pytest.raises(ApiError) as exc:
            client.request(
                "POST", "/api/v0/add", content=body, headers={"Content-Type": content_type}
            )
        assert error_of(exc, 413, "payload_too_large").details["limit"] == 100_000
        with pytest.raises(ApiError) as exc:  # chunked, no Content-Length: cut off while streaming
            client.request(
                "POST",
                "/api/v0/add",
                content=iter([body[:60_000], body[60_000:]]),
                content_sha256=hashlib.sha256(body).hexdigest(),
                headers={"Content-Type": content_type},
            )
        error_of(exc, 413, "payload_too_large")
    nothing_stored(small_cas)


@pytest.mark.parametrize(
    "path",
    [
        "/api/v0/add",
        "/api/v0/block/put",
        "/api/v0/dag/import",
        f"/api/v0/pin/add?arg={UNKNOWN}",
        f"/api/v0/pin/rm?arg={UNKNOWN}",
        "/api/v0/repo/gc",
    ],
)
def test_unsigned_write_is_401(shared_cas_service: ServiceProcess, path: str) -> None:
    body, content_type = multipart(("f", b"Hello world"))
    with store_unchanged(shared_cas_service):
        response = httpx.post(
            shared_cas_service.url + path, content=body, headers={"Content-Type": content_type}
        )
    assert response.status_code == 401
    assert response.json()["error"]["details"]["header"].startswith("X-Robocloud-")
    assert list((shared_cas_service.data_dir / "spool").iterdir()) == []


def test_unpinning_another_robots_pin_is_403(cas_service: ServiceProcess) -> None:
    owner, other = Identity.generate(), Identity.generate()
    with Cas(cas_service.url, owner) as mine, Cas(cas_service.url, other) as theirs:
        cid = mine.add_bytes(b"my data")
        with pytest.raises(ApiError) as exc:
            theirs.unpin(cid)
        error = error_of(exc, 403, "pin_not_owned")
        assert error.details == {"cid": str(cid), "address": other.address}
        assert mine.pins()[str(cid)]["Owners"] == [owner.address]
        theirs.pin(cid)
        theirs.unpin(cid)
        assert mine.pins()[str(cid)]["Owners"] == [owner.address]
        mine.unpin(cid)
        assert mine.pins() == {}
        with pytest.raises(ApiError) as exc:
            mine.unpin(cid)
        error_of(exc, 404, "not_pinned")


def test_bad_import_options_are_400(signed: ServiceClient, cas_service: ServiceProcess) -> None:
    body, content_type = multipart(("f", b"x"))
    for params, field in [({"chunker": "rabin-1-2-3"}, "chunker"), ({"cid-version": 7}, "cid")]:
        with pytest.raises(ApiError) as exc:
            signed.request(
                "POST",
                "/api/v0/add",
                params=params,
                content=body,
                headers={"Content-Type": content_type},
            )
        assert field in error_of(exc, 400, "invalid_import_options").message
    with pytest.raises(ApiError) as exc:
        signed.request(
            "POST", "/api/v0/add", content=b"plain", headers={"Content-Type": "text/plain"}
        )
    assert error_of(exc, 415, "unsupported_media_type").details["header"] == "Content-Type"
    nothing_stored(cas_service)
