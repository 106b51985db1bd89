"""Each layer of the request guard, alone, in process over ``httpx.ASGITransport``.

The layers wrap small ASGI apps that report what reached them, so each test shows what a
layer lets through, what it answers itself, and what it hands down.
"""

from __future__ import annotations

import asyncio
import errno
import hashlib
import logging
import shutil
import sqlite3
import threading
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import anyio
import httpx
import pytest
from prometheus_client import Counter
from prometheus_client.parser import text_string_to_metric_families
from starlette.requests import Request
from starlette.responses import JSONResponse
from starlette.routing import Route, Router
from starlette.types import ASGIApp, Receive, Scope, Send

from robocloud.identity import Identity
from robocloud.signing import HEADER_AUDIENCE, HEADER_NONCE, sign_request
from services.common.audience import ServiceAudience
from services.common.auth import AnySigner, Authorizer
from services.common.disk import DiskReserve
from services.common.errors import Forbidden, ServiceError, Unavailable
from services.common.logs import request_id_var
from services.common.metrics import ServiceMetrics
from services.common.middleware import (
    UNKNOWN_SIGNER,
    AccessLogLayer,
    BodyLimitLayer,
    DiskReserveLayer,
    RequestIdLayer,
    SignatureLayer,
)
from services.common.nonces import NonceStore, StrangerNonces

AUDIENCE = "cas@local"


def call(app: ASGIApp, method: str, path: str, **kwargs: Any) -> httpx.Response:
    async def go() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            return await client.request(method, path, **kwargs)

    return asyncio.run(go())


async def echo(scope: Scope, receive: Receive, send: Send) -> None:
    """Reads the whole body and answers what reached it: body size, request id, signer."""
    body = b""
    while True:
        message = await receive()
        body += message.get("body", b"")
        if not message.get("more_body", False):
            break
    signature = scope.get("state", {}).get("signature")
    answer = {
        "body_bytes": len(body),
        "request_id": request_id_var.get(),
        "signer": signature.address if signature else None,
    }
    await JSONResponse(answer)(scope, receive, send)


def never_called(scope: Scope, receive: Receive, send: Send) -> Awaitable[None]:
    raise AssertionError("the layer should have answered without calling the app")


def error_of(response: httpx.Response, status: int, code: str) -> dict[str, Any]:
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/json"
    error: dict[str, Any] = response.json()["error"]
    assert error["code"] == code
    return error


# RequestIdLayer


def test_request_id_is_generated_kept_or_replaced_and_seen_by_the_app() -> None:
    app = RequestIdLayer(echo)
    generated = call(app, "GET", "/")
    assert len(generated.headers["x-request-id"]) == 32
    assert generated.json()["request_id"] == generated.headers["x-request-id"]
    kept = call(app, "GET", "/", headers={"X-Request-Id": "robot-req-0001"})
    assert kept.headers["x-request-id"] == kept.json()["request_id"] == "robot-req-0001"
    for unsafe in ("short", "has space in it", "x" * 65, "semi;colon-1234"):
        replaced = call(app, "GET", "/", headers={"X-Request-Id": unsafe})
        assert replaced.headers["x-request-id"] != unsafe
        assert len(replaced.headers["x-request-id"]) == 32
    assert request_id_var.get() == "-", "the id does not leak out of the request"


def test_unhandled_exception_is_a_500_in_the_error_model_logged_with_the_id(
    caplog: pytest.LogCaptureFixture,
) -> None:
    seen: list[str] = []

    async def broken(scope: Scope, receive: Receive, send: Send) -> None:
        seen.append(request_id_var.get())
        raise RuntimeError("secret internal detail")

    with caplog.at_level(logging.ERROR, logger="robocloud.http"):
        response = call(
            RequestIdLayer(broken), "GET", "/", headers={"X-Request-Id": "req-00000042"}
        )
    error = error_of(response, 500, "internal_error")
    assert error["request_id"] == response.headers["x-request-id"] == seen[0] == "req-00000042"
    assert "secret" not in response.text
    [record] = [r for r in caplog.records if r.getMessage() == "unhandled error"]
    assert record.exc_info is not None
    assert "secret internal detail" in str(record.exc_info[1])


class RecordNotStored(Exception):
    """A domain module's own error, raised from the disk's."""


def sqlite_full(path: Path) -> sqlite3.Error:
    """SQLite's own ``SQLITE_FULL``: a database capped at two pages, written past them."""
    with sqlite3.connect(path) as db:
        db.execute("PRAGMA max_page_count = 2")
        db.execute("CREATE TABLE t (v BLOB)")
        try:
            db.execute("INSERT INTO t VALUES (?)", (bytes(10_000),))
        except sqlite3.Error as exc:
            return exc
    raise AssertionError("SQLite stored past its page cap")


def raised_from(cause: Exception) -> Exception:
    try:
        raise RecordNotStored("the record log could not append") from cause
    except RecordNotStored as exc:
        return exc


@pytest.mark.parametrize(
    "full",
    [
        OSError(errno.ENOSPC, "No space left on device", "/data/cas/spool/part"),
        OSError(errno.EDQUOT, "Disk quota exceeded"),
        "sqlite",
        "raised from",
    ],
)
def test_a_full_disk_is_a_507_logged_in_one_line(
    full: Exception | str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The robot learns that the failure is the service's and lasts until its operator acts
    (not a 500 it cannot tell from a bug); the operator gets one line, not a traceback."""
    cause = None
    if full == "sqlite":
        full = sqlite_full(tmp_path / "capped.sqlite")
    elif full == "raised from":
        cause = OSError(errno.ENOSPC, "No space left on device")
        full = raised_from(cause)
    assert isinstance(full, Exception)

    async def writes(scope: Scope, receive: Receive, send: Send) -> None:
        raise full

    with caplog.at_level(logging.INFO, logger="robocloud.http"):
        response = call(RequestIdLayer(writes), "POST", "/", headers={"X-Request-Id": "req-full-1"})
    error = error_of(response, 507, "insufficient_storage")
    assert error["message"].startswith("the service's disk is full")
    assert error["request_id"] == "req-full-1"
    assert "/data/cas" not in response.text
    [record] = caplog.records
    assert (record.levelname, record.exc_info) == ("ERROR", None)
    assert record.getMessage() == f"the disk is full: {cause or full}"


def test_other_os_errors_stay_500() -> None:
    async def refused(scope: Scope, receive: Receive, send: Send) -> None:
        raise raised_from(OSError(errno.EACCES, "Permission denied"))

    error_of(call(RequestIdLayer(refused), "POST", "/"), 500, "internal_error")


def test_exception_after_the_answer_started_is_not_answered_twice() -> None:
    async def breaks_mid_answer(scope: Scope, receive: Receive, send: Send) -> None:
        await send({"type": "http.response.start", "status": 200, "headers": []})
        raise RuntimeError("after the start")

    with pytest.raises(RuntimeError, match="after the start"):
        call(RequestIdLayer(breaks_mid_answer), "GET", "/")


# AccessLogLayer


def routed_app() -> Router:
    """A bare router (no Starlette app around it, whose error middleware would answer 500)."""

    async def item(request: Request) -> JSONResponse:
        return JSONResponse({"id": request.path_params["item_id"]})

    async def broken(request: Request) -> JSONResponse:
        raise RuntimeError("boom")

    return Router(routes=[Route("/items/{item_id}", item), Route("/broken", broken)])


def requests_counted(metrics: ServiceMetrics) -> dict[tuple[str, str, str], float]:
    counted = {}
    for metric in metrics.registry.collect():
        for sample in metric.samples:
            if sample.name == "robocloud_http_requests_total":
                labels = sample.labels
                counted[(labels["method"], labels["route"], labels["status"])] = sample.value
    return counted


def test_metrics_are_labelled_by_route_template_never_by_raw_path() -> None:
    metrics = ServiceMetrics("test")
    app = AccessLogLayer(routed_app(), metrics)
    for item_id in ("a", "b", "c"):
        assert call(app, "GET", f"/items/{item_id}").json() == {"id": item_id}
    assert call(app, "GET", "/nowhere/1").status_code == 404
    assert call(app, "GET", "/nowhere/2").status_code == 404
    assert requests_counted(metrics) == {
        ("GET", "/items/{item_id}", "200"): 3.0,
        ("GET", "unmatched", "404"): 2.0,
    }


def test_metrics_count_methods_outside_http_as_other_so_a_client_cannot_grow_them() -> None:
    # HTTP/1.1 lets any token be a method: one label value per token would let an unsigned
    # client grow /metrics (and the service's memory) without bound.
    metrics = ServiceMetrics("test")
    app = AccessLogLayer(routed_app(), metrics)
    for method in ("M0001", "M0002", "BREW", "PATCH"):
        call(app, method, "/nowhere")
    assert requests_counted(metrics) == {
        ("other", "unmatched", "404"): 3.0,
        ("PATCH", "unmatched", "404"): 1.0,
    }
    assert b"M0001" not in metrics.render()


def test_exception_passing_through_counts_as_500_and_is_logged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    metrics = ServiceMetrics("test")
    app = RequestIdLayer(AccessLogLayer(routed_app(), metrics))
    with caplog.at_level(logging.INFO, logger="robocloud.http"):
        assert call(app, "GET", "/broken").status_code == 500
    assert requests_counted(metrics) == {("GET", "/broken", "500"): 1.0}
    [line] = [r for r in caplog.records if r.getMessage() == "request"]
    assert (line.method, line.path, line.route, line.status) == ("GET", "/broken", "/broken", 500)  # type: ignore[attr-defined]


def test_access_log_names_the_signer_of_a_signed_request(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    robot = Identity.generate()
    app = AccessLogLayer(signature_layer(tmp_path, echo), ServiceMetrics("test"))
    with caplog.at_level(logging.INFO, logger="robocloud.http"):
        assert call(app, "POST", "/w", headers=signed(robot, "/w")).status_code == 200
    [line] = [r for r in caplog.records if r.getMessage() == "request"]
    assert line.signer == robot.address  # type: ignore[attr-defined]
    assert line.status == 200  # type: ignore[attr-defined]


def test_services_register_their_own_collectors_beside_the_layers() -> None:
    metrics = ServiceMetrics("test")
    Counter("robocloud_test_things", "Things.", registry=metrics.registry).inc()
    rendered = metrics.render().decode()
    assert "robocloud_test_things_total 1.0" in rendered


# BodyLimitLayer


def test_declared_oversized_body_is_413_before_the_app_runs() -> None:
    app = BodyLimitLayer(never_called, default_limit=100)
    response = call(app, "POST", "/x", content=b"x" * 101)
    error = error_of(response, 413, "payload_too_large")
    assert error["details"] == {"header": "Content-Length", "limit": 100}


def test_streamed_body_is_cut_off_when_it_passes_the_limit() -> None:
    """No Content-Length (chunked): the meter counts and refuses once the limit is passed."""
    reached: list[int] = []

    async def reads_until_refused(scope: Scope, receive: Receive, send: Send) -> None:
        while True:
            message = await receive()
            reached.append(len(message.get("body", b"")))
            if not message.get("more_body", False):
                break
        await JSONResponse({"read": sum(reached)})(scope, receive, send)

    def chunks() -> Any:
        async def gen() -> Any:
            for _ in range(10):
                yield b"y" * 40

        return gen()

    app = BodyLimitLayer(reads_until_refused, default_limit=100)
    response = call(app, "POST", "/x", content=chunks())
    error = error_of(response, 413, "payload_too_large")
    assert error["details"] == {"limit": 100}
    assert sum(reached) <= 100, "the chunk that passed the limit never reached the app"


def test_body_within_the_limit_reaches_the_app_whole() -> None:
    app = BodyLimitLayer(echo, default_limit=100)
    assert call(app, "POST", "/x", content=b"z" * 100).json()["body_bytes"] == 100


def test_longest_matching_prefix_sets_the_limit() -> None:
    layer = BodyLimitLayer(echo, default_limit=10, limits={"/up": 1000, "/up/small": 20})
    assert (layer.limit_for("/other"), layer.limit_for("/up/big")) == (10, 1000)
    assert layer.limit_for("/up/small/x") == 20
    assert call(layer, "POST", "/up/big", content=b"a" * 500).json()["body_bytes"] == 500
    error = error_of(call(layer, "POST", "/up/small", content=b"a" * 21), 413, "payload_too_large")
    assert error["details"]["limit"] == 20


# SignatureLayer


def signature_layer(
    tmp_path: Path,
    app: ASGIApp,
    *,
    authorizer: Authorizer | None = None,
    audience: ServiceAudience | None = None,
    nonces: NonceStore | None = None,
) -> SignatureLayer:
    return SignatureLayer(
        app,
        audience=audience or ServiceAudience("cas", "local", source="test"),
        nonces=nonces if nonces is not None else NonceStore(tmp_path / "nonces.log", 300),
        authorizer=authorizer or AnySigner(),
        max_clock_skew_s=300,
        unsigned_paths=["/rpc"],
    )


def signed(
    robot: Identity, path: str, body: bytes = b"", audience: str = AUDIENCE, **kwargs: Any
) -> dict[str, str]:
    digest = hashlib.sha256(body).hexdigest()
    return sign_request(robot.account, audience, "POST", path, "", digest, **kwargs)


def test_reads_and_unsigned_paths_pass_without_a_signature(tmp_path: Path) -> None:
    app = signature_layer(tmp_path, echo)
    assert call(app, "GET", "/anything").json()["signer"] is None
    assert call(app, "POST", "/rpc", content=b"{}").json()["body_bytes"] == 2


def test_a_write_no_route_takes_goes_on_unsigned_to_the_app_s_answer(tmp_path: Path) -> None:
    """The app answers it 404 or 405 and writes nothing; a signature would change neither."""
    layer = signature_layer(tmp_path, echo)
    layer.routed = lambda scope: scope["path"] != "/nowhere"
    assert call(layer, "POST", "/nowhere", content=b"{}").json()["signer"] is None
    error_of(call(layer, "POST", "/w", content=b"{}"), 401, "missing_signature_header")


def test_unsigned_write_is_401_before_the_app_runs(tmp_path: Path) -> None:
    response = call(signature_layer(tmp_path, never_called), "POST", "/w", content=b"{}")
    error = error_of(response, 401, "missing_signature_header")
    assert error["details"] == {"header": "X-Robocloud-Address"}


def test_signed_write_reaches_the_app_with_its_verified_signer(tmp_path: Path) -> None:
    robot = Identity.generate()
    body = b'{"a": 1}'
    response = call(
        signature_layer(tmp_path, echo),
        "POST",
        "/w",
        content=body,
        headers=signed(robot, "/w", body),
    )
    assert response.json() == {"body_bytes": len(body), "request_id": "-", "signer": robot.address}


def test_wrong_audience_is_401_naming_both_and_burns_no_nonce(tmp_path: Path) -> None:
    robot = Identity.generate()
    app = signature_layer(tmp_path, echo)
    nonce = "fixed-nonce-00000001"
    for other in ("ledger@local", "cas@1337:0x" + "ab" * 20):
        headers = signed(robot, "/w", audience=other, nonce=nonce)
        error = error_of(call(app, "POST", "/w", headers=headers), 401, "wrong_audience")
        assert error["details"] == {
            "header": HEADER_AUDIENCE,
            "expected": AUDIENCE,
            "received": other,
        }
    own = call(app, "POST", "/w", headers=signed(robot, "/w", nonce=nonce))
    assert own.json()["signer"] == robot.address, "the refused requests left the nonce unused"


def test_v1_request_is_401_naming_v2(tmp_path: Path) -> None:
    robot = Identity.generate()
    headers = signed(robot, "/w")
    del headers[HEADER_AUDIENCE]
    response = call(signature_layer(tmp_path, never_called), "POST", "/w", headers=headers)
    error = error_of(response, 401, "unsupported_signature_version")
    assert "ROBOCLOUD-REQUEST-V2" in error["message"]
    assert error["details"] == {"header": HEADER_AUDIENCE}


def test_replayed_nonce_is_401(tmp_path: Path) -> None:
    robot = Identity.generate()
    app = signature_layer(tmp_path, echo)
    headers = signed(robot, "/w")
    assert call(app, "POST", "/w", headers=headers).status_code == 200
    error = error_of(call(app, "POST", "/w", headers=headers), 401, "replayed_nonce")
    assert error["details"] == {"header": HEADER_NONCE}


def test_a_full_nonce_store_is_503_with_retry_after_and_records_nothing(tmp_path: Path) -> None:
    robot = Identity.generate()
    nonces = NonceStore(tmp_path / "nonces.log", 300, max_entries=1)
    app = signature_layer(tmp_path, echo, nonces=nonces)
    first = signed(robot, "/w")
    assert call(app, "POST", "/w", headers=first).status_code == 200
    response = call(app, "POST", "/w", headers=signed(robot, "/w"))
    error = error_of(response, 503, "nonce_store_full")
    assert error["details"]["limit"] == 1
    assert response.headers["retry-after"] == str(error["details"]["retry_after"])
    assert len(nonces) == 1
    error_of(call(app, "POST", "/w", headers=first), 401, "replayed_nonce")


def test_one_signer_past_its_share_of_nonces_is_429_and_others_still_write(
    tmp_path: Path,
) -> None:
    """One robot signing as fast as it can used to fill the whole store and lock every
    other robot out of writing for the rest of the clock window."""
    busy, other = Identity.generate(), Identity.generate()
    nonces = NonceStore(tmp_path / "nonces.log", 300, max_entries=10, max_per_address=3)
    app = signature_layer(tmp_path, echo, nonces=nonces)
    for _ in range(3):
        assert call(app, "POST", "/w", headers=signed(busy, "/w")).json()["signer"] == busy.address
    response = call(app, "POST", "/w", headers=signed(busy, "/w"))
    error = error_of(response, 429, "nonce_quota_exceeded")
    assert error["details"]["limit"] == 3
    assert 299 <= error["details"]["retry_after"] <= 302
    assert response.headers["retry-after"] == str(error["details"]["retry_after"])
    assert len(nonces) == 3
    assert call(app, "POST", "/w", headers=signed(other, "/w")).json()["signer"] == other.address
    assert len(nonces) == 4


class HeldStore(NonceStore):
    """A nonce store whose recording waits until the test lets it go (a slow fsync)."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, 300)
        self.entered = threading.Event()
        self.release = threading.Event()

    def use(self, address: str, nonce: str, timestamp: int) -> bool:
        self.entered.set()
        self.release.wait(timeout=10)
        return super().use(address, nonce, timestamp)


def test_other_requests_are_served_while_a_nonce_is_being_made_durable(tmp_path: Path) -> None:
    """The journal's fsync runs on a worker thread: on the event loop it held every request
    behind the disk."""
    robot = Identity.generate()
    nonces = HeldStore(tmp_path / "nonces.log")
    app = signature_layer(tmp_path, echo, nonces=nonces)

    async def go() -> None:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            write = asyncio.create_task(client.post("/w", headers=signed(robot, "/w")))
            assert await anyio.to_thread.run_sync(nonces.entered.wait, 10)
            assert (await client.get("/r")).status_code == 200
            assert not write.done(), "the write waits for its nonce to be durable"
            nonces.release.set()
            assert (await write).json()["signer"] == robot.address

    asyncio.run(go())


class Listed:
    """An authorizer that lets in the addresses it holds (the registry's answer, fixed) and
    refuses others with ``refusal`` (by default the registry's answer for a stranger)."""

    def __init__(self, refusal: Callable[[str], ServiceError] | None = None) -> None:
        self.addresses: set[str] = set()
        self.refusal = refusal or stranger
        self.asked = 0

    async def authorize(self, address: str, role: str | None = None) -> None:
        self.asked += 1
        if address not in self.addresses:
            raise self.refusal(address)

    async def holds_role(self, address: str, role: str) -> bool:
        return False

    def close(self) -> None:
        return None


def stranger(address: str) -> ServiceError:
    return Forbidden(
        f"address {address} is not a registered robot",
        code=UNKNOWN_SIGNER,
        details={"address": address},
    )


def test_a_stranger_refused_leaves_no_nonce(tmp_path: Path) -> None:
    """Self-made keys cost nothing: were their nonces kept, they would fill the store."""
    robot = Identity.generate()
    nonces = NonceStore(tmp_path / "nonces.log", 300)
    app = signature_layer(tmp_path, never_called, authorizer=Listed(), nonces=nonces)
    for _ in range(3):
        first = error_of(call(app, "POST", "/w", headers=signed(robot, "/w")), 403, UNKNOWN_SIGNER)
        assert first["details"] == {"address": robot.address}
    assert len(nonces) == 0
    assert (tmp_path / "nonces.log").read_text() == ""


def test_a_strangers_refused_request_is_not_replayed_into_success_once_approved(
    tmp_path: Path,
) -> None:
    """It was: a copy sent within the clock window after the key's approval succeeded once,
    though its robot had moved on after the 403."""
    robot = Identity.generate()
    listed = Listed()
    app = signature_layer(tmp_path, echo, authorizer=listed)
    headers = signed(robot, "/w")
    error_of(call(app, "POST", "/w", headers=headers), 403, UNKNOWN_SIGNER)
    listed.addresses.add(robot.address)
    for _ in range(2):
        error_of(call(app, "POST", "/w", headers=headers), 401, "replayed_nonce")
    assert call(app, "POST", "/w", headers=signed(robot, "/w")).json()["signer"] == robot.address


def test_strangers_nonces_are_bounded_and_forgotten_with_their_window() -> None:
    now = [1000.0]
    strangers = StrangerNonces(window_s=300, limit=2, clock=lambda: now[0])
    for nonce in ("a", "b", "c"):
        strangers.remember("0xS", nonce, 1000)
    assert [strangers.refused("0xS", nonce) for nonce in "abc"] == [False, True, True]
    now[0] = 1301.0
    assert not strangers.refused("0xS", "c"), "its timestamp left the window"
    strangers.remember("0xT", "d", 1301)
    assert len(strangers) == 1, "expired ones go as new ones come"


def test_a_replay_is_refused_though_the_authorizer_is_asked_first(tmp_path: Path) -> None:
    robot = Identity.generate()
    listed = Listed()
    listed.addresses.add(robot.address)
    app = signature_layer(tmp_path, echo, authorizer=listed)
    headers = signed(robot, "/w")
    assert call(app, "POST", "/w", headers=headers).json()["signer"] == robot.address
    error_of(call(app, "POST", "/w", headers=headers), 401, "replayed_nonce")
    assert listed.asked == 2


def test_copies_of_a_request_racing_past_the_authorizer_let_one_through(tmp_path: Path) -> None:
    """The nonce is checked and recorded in one step after the authorizer's await."""
    robot = Identity.generate()
    listed = Listed()
    listed.addresses.add(robot.address)
    app = signature_layer(tmp_path, echo, authorizer=listed)
    headers = signed(robot, "/w")

    async def race() -> list[int]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            copies = [client.post("/w", headers=headers) for _ in range(8)]
            return [response.status_code for response in await asyncio.gather(*copies)]

    assert sorted(asyncio.run(race())) == [200] + [401] * 7


@pytest.mark.parametrize(
    "refusal",
    [
        lambda address: Forbidden("awaits approval", code="registration_pending"),
        lambda address: Unavailable("cannot reach the ledger", code="ledger_unreachable"),
    ],
    ids=["pending-robot", "ledger-down"],
)
def test_other_refusals_use_up_the_nonce_so_they_are_final(
    tmp_path: Path, refusal: Callable[[str], ServiceError]
) -> None:
    """A request refused (403 for a known robot, 503 while the ledger is down, after which the
    SDK retries with a fresh nonce) cannot be replayed into success once the signer is let in."""
    robot = Identity.generate()
    listed = Listed(refusal)
    app = signature_layer(tmp_path, never_called, authorizer=listed)
    headers = signed(robot, "/w")
    first = call(app, "POST", "/w", headers=headers)
    assert first.status_code in (403, 503)
    listed.addresses.add(robot.address)
    error_of(call(app, "POST", "/w", headers=headers), 401, "replayed_nonce")


def test_unknown_audience_is_503_until_learned(tmp_path: Path) -> None:
    robot = Identity.generate()
    audience = ServiceAudience("cas", source="the ledger at http://ledger")
    app = signature_layer(tmp_path, echo, audience=audience)
    deployment = "1337:0x" + "ab" * 20
    headers = signed(robot, "/w", audience=f"cas@{deployment}")
    error = error_of(call(app, "POST", "/w", headers=headers), 503, "audience_unknown")
    assert "the ledger at http://ledger" in error["message"]
    audience.learn(deployment)
    assert call(app, "POST", "/w", headers=headers).json()["signer"] == robot.address


def test_body_not_matching_the_signed_digest_is_400_when_it_ends(tmp_path: Path) -> None:
    robot = Identity.generate()
    headers = signed(robot, "/w", b"what was signed")
    response = call(
        signature_layer(tmp_path, echo), "POST", "/w", content=b"what was sent", headers=headers
    )
    error = error_of(response, 400, "body_digest_mismatch")
    assert error["details"]["header"] == "X-Robocloud-Content-SHA256"


# DiskReserveLayer

MORE_THAN_ANY_DISK = 1 << 60


def reserve_layer(tmp_path: Path, app: ASGIApp, reserve_bytes: int) -> DiskReserveLayer:
    return DiskReserveLayer(
        app, reserve=DiskReserve(tmp_path, reserve_bytes), storing_paths=["/up"]
    )


def test_a_write_that_would_take_the_reserve_is_507_before_the_app_runs(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    app = reserve_layer(tmp_path, never_called, MORE_THAN_ANY_DISK)
    with caplog.at_level(logging.WARNING, logger="robocloud.http"):
        response = call(app, "POST", "/up/add", content=b"x" * 10)
    error = error_of(response, 507, "insufficient_storage")
    assert error["details"]["reserve_bytes"] == MORE_THAN_ANY_DISK
    assert 0 <= error["details"]["free_bytes"] < MORE_THAN_ANY_DISK
    assert error["details"]["declared_bytes"] == 10
    assert error["message"].startswith(f"the service keeps {MORE_THAN_ANY_DISK} bytes of its")
    [record] = caplog.records
    assert record.getMessage() == "write refused: the disk is down to its reserve"
    assert record.__dict__["reserve_bytes"] == MORE_THAN_ANY_DISK


def test_a_declared_body_larger_than_the_room_left_is_507_naming_content_length(
    tmp_path: Path,
) -> None:
    app = reserve_layer(tmp_path, never_called, 1)
    response = call(
        app, "POST", "/up", content=b"{}", headers={"Content-Length": str(MORE_THAN_ANY_DISK)}
    )
    error = error_of(response, 507, "insufficient_storage")
    assert error["details"]["header"] == "Content-Length"
    assert error["details"]["declared_bytes"] == MORE_THAN_ANY_DISK
    assert f"this write of {MORE_THAN_ANY_DISK} bytes is refused" in error["message"]


def test_reads_other_paths_and_a_zero_reserve_pass_whatever_the_disk(tmp_path: Path) -> None:
    """Deletions (``pin/rm``, ``repo/gc``) are not storing paths: they free the space."""
    assert call(reserve_layer(tmp_path, echo, MORE_THAN_ANY_DISK), "GET", "/up").status_code == 200
    to_other = call(reserve_layer(tmp_path, echo, MORE_THAN_ANY_DISK), "POST", "/rm", content=b"1")
    assert to_other.json()["body_bytes"] == 1
    unreserved = call(reserve_layer(tmp_path, echo, 0), "POST", "/up", content=b"x" * 1000)
    assert unreserved.json()["body_bytes"] == 1000


def test_a_write_with_room_left_reaches_the_app_whole(tmp_path: Path) -> None:
    app = reserve_layer(tmp_path, echo, 1)
    assert call(app, "POST", "/up", content=b"z" * 3_000_000).json()["body_bytes"] == 3_000_000


def test_metrics_show_the_disks_free_space_beside_its_reserve(tmp_path: Path) -> None:
    metrics = ServiceMetrics("test")
    metrics.watch_disk(DiskReserve(tmp_path, 12345))
    samples = {
        sample.name: sample.value
        for family in text_string_to_metric_families(metrics.render().decode())
        for sample in family.samples
    }
    assert samples["robocloud_disk_reserve_bytes"] == 12345
    free = shutil.disk_usage(tmp_path).free
    assert abs(samples["robocloud_disk_free_bytes"] - free) < 0.01 * free


def test_a_write_refused_for_the_reserve_is_signed_first_and_uses_its_nonce(
    tmp_path: Path,
) -> None:
    """A stranger learns nothing of the disk, and a refused write cannot be replayed into
    success once space is freed."""
    app = signature_layer(tmp_path, reserve_layer(tmp_path, never_called, MORE_THAN_ANY_DISK))
    error_of(call(app, "POST", "/up", content=b"{}"), 401, "missing_signature_header")
    headers = signed(Identity.generate(), "/up", b"{}")
    error_of(call(app, "POST", "/up", content=b"{}", headers=headers), 507, "insufficient_storage")
    error_of(call(app, "POST", "/up", content=b"{}", headers=headers), 401, "replayed_nonce")


def test_layers_compose_outermost_request_id_first(tmp_path: Path) -> None:
    """In the order create_app installs them, a refusal deep inside carries the request id."""
    metrics = ServiceMetrics("test")
    app = RequestIdLayer(
        AccessLogLayer(BodyLimitLayer(signature_layer(tmp_path, echo), default_limit=10), metrics)
    )
    response = call(app, "POST", "/w", content=b"{}", headers={"X-Request-Id": "compose-0001"})
    error = error_of(response, 401, "missing_signature_header")
    assert error["request_id"] == "compose-0001"
    too_big = call(app, "POST", "/w", content=b"x" * 11)
    assert (
        error_of(too_big, 413, "payload_too_large")["request_id"] == too_big.headers["x-request-id"]
    )
    assert requests_counted(metrics) == {
        ("POST", "unmatched", "401"): 1.0,
        ("POST", "unmatched", "413"): 1.0,
    }
