"""Hostile input at every public route of real service processes: no 500, no crash.

Routes come from each service's own OpenAPI document, so a new route is fuzzed without a
change here. Write routes are reached with valid signatures (the SDK signs whatever body
hypothesis makes), so the fuzzing gets past the guard into the handlers. After each service's
run the process must still be alive and answer ``/healthz``.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robocloud.client import ServiceClient
from robocloud.errors import ApiError
from robocloud.identity import Identity
from tests.procs import ServiceProcess

SERVICES = {
    "cas": {"ROBOCLOUD_CAS_GC_INTERVAL_S": "0"},
    "ledger": {"ROBOCLOUD_LEDGER_ADMIN_PASSPHRASE": "fuzz-tests-only"},
    "storage": {},
}
EXAMPLES = 150
VALID_CID = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"


@dataclass(frozen=True)
class Route:
    method: str
    template: str

    def path(self, segment: str) -> str:
        return re.sub(r"\{[^}]+\}", lambda _: segment, self.template)


@dataclass
class Target:
    process: ServiceProcess
    routes: list[Route]
    signed: ServiceClient
    raw: httpx.Client


@pytest.fixture(scope="module", params=sorted(SERVICES))
def target(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Target]:
    name: str = request.param
    data_dir: Path = tmp_path_factory.mktemp(f"fuzz-{name}") / name
    process = ServiceProcess(name, data_dir, SERVICES[name]).start(timeout_s=60)
    try:
        document = httpx.get(f"{process.url}/openapi.json", timeout=30).json()
        routes = [
            Route(method.upper(), template)
            for template, operations in document["paths"].items()
            for method in operations
        ]
        with (
            ServiceClient(process.url, Identity.generate(), retries=0, timeout=30) as signed,
            httpx.Client(base_url=process.url, timeout=30) as raw,
        ):
            yield Target(process, routes, signed, raw)
        assert process.process is not None
        assert process.process.poll() is None, f"{name} crashed; see {process.log_path}"
        health = httpx.get(f"{process.url}/healthz", timeout=30)
        assert health.json()["status"] == "ok"
    finally:
        process.stop()


def _check(response_status: int, body: bytes, headers: httpx.Headers, method: str) -> None:
    assert response_status < 500, (response_status, body[:500])
    if response_status >= 400 and method != "HEAD":
        error = json.loads(body)["error"]
        assert re.fullmatch(r"[a-z0-9_]+", error["code"])
        assert error["request_id"] == headers["x-request-id"]


def _send_signed(target: Target, route: Route, segment: str, **kwargs: Any) -> None:
    try:
        response = target.signed.request(route.method, route.path(segment), **kwargs)
    except ApiError as exc:
        refused = exc
    else:
        _check(response.status_code, response.content, response.headers, route.method)
        return
    assert refused.status < 500, (route, refused)
    assert re.fullmatch(r"[a-z0-9_]+", refused.code)


def _nested(depth: int) -> bytes:
    return b"[" * depth + b"]" * depth


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=50),
    lambda children: (
        st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=10), children, max_size=5)
    ),
    max_leaves=30,
)


def _multipart(parts: list[tuple[str, bytes]]) -> bytes:
    """A body for ``Content-Type: multipart/form-data; boundary=x``."""
    body = b""
    for disposition, data in parts:
        body += (
            b"--x\r\nContent-Disposition: " + disposition.encode() + b"\r\n\r\n" + data + b"\r\n"
        )
    return body + b"--x--\r\n"


multipart_bodies = st.lists(
    st.tuples(
        st.one_of(
            st.just('form-data; name="file"; filename="a.bin"'),
            st.just('form-data; name="file"; filename="' + "n" * 10_000 + '"'),
            st.just('form-data; name="file"; filename="../../etc/passwd"'),
            st.text(max_size=40).map(lambda text: text.replace("\r", "").replace("\n", "")),
        ),
        st.binary(max_size=300),
    ),
    max_size=6,
).map(_multipart)

hostile_bodies = st.one_of(
    multipart_bodies,
    json_values.map(lambda value: json.dumps(value).encode()),
    st.binary(max_size=2000),
    st.sampled_from(
        [
            _nested(100_000),
            b'{"a":' * 50_000 + b"1" + b"}" * 50_000,
            b'{"jsonrpc": "2.0", "id": NaN, "method": "eth_chainId"}',
            b'{"jsonrpc": "2.0", "id": ' + b"9" * 5000 + b', "method": "eth_chainId"}',
            b'{"address": "' + b"0" * 100_000 + b'"}',
            b"\xff\xfe\x00\x00",
            # A CAR header whose CBOR nests deeper than anything real.
            bytes([0xFF, 0x01]) + b"\x81" * 255,
            b"\x0a" + b"\xa1\x65roots" + b"\x81" * 10_000,
        ]
    ),
)

content_types = st.sampled_from(
    [
        "application/json",
        "application/octet-stream",
        "multipart/form-data; boundary=x",
        "multipart/form-data",
        "multipart/form-data; boundary=" + "b" * 5000,
        "text/plain; charset=utf-8",
        "application/vnd.ipld.car",
    ]
)

segments = st.one_of(
    st.sampled_from(
        [VALID_CID, "Qm" + "1" * 44, "9" * 5000, "0x" + "ab" * 20, "%00", "..", "a" * 600]
    ),
    st.text(alphabet=st.characters(blacklist_categories=["Cs"]), min_size=1, max_size=40).map(
        lambda text: quote(text, safe="")
    ),
)

query_params = st.dictionaries(
    st.sampled_from(
        [
            *("arg", "format", "dag-scope", "cid-version", "chunker", "offset", "length"),
            *("limit", "since", "cid", "advertiser", "epoch", "node", "pin", "raw-leaves"),
        ]
    ),
    st.one_of(st.text(max_size=30), st.just("9" * 5000), st.just(VALID_CID)),
    max_size=4,
)

header_sets = st.dictionaries(
    st.sampled_from(["Range", "Accept", "If-None-Match", "Cache-Control", "X-Request-Id"]),
    st.one_of(
        st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=60).map(
            str.strip  # surrounding spaces are not a header value any client can send
        ),
        st.just("bytes=" + "9" * 5000 + "-"),
        st.just("bytes=0-" + "9" * 5000),
        st.just("bytes=" + ",".join(["0-1"] * 2000)),
        st.just("x" * 4000),
    ),
    max_size=3,
)

FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@FUZZ
@given(data=st.data())
def test_signed_bodies_never_crash_a_route(target: Target, data: st.DataObject) -> None:
    route = data.draw(st.sampled_from([r for r in target.routes if r.method == "POST"]))
    _send_signed(
        target,
        route,
        data.draw(segments),
        content=data.draw(hostile_bodies),
        headers={"Content-Type": data.draw(content_types)},
        params=data.draw(query_params),
    )


@FUZZ
@given(data=st.data())
def test_unsigned_requests_with_hostile_headers_and_queries(
    target: Target, data: st.DataObject
) -> None:
    route = data.draw(st.sampled_from(target.routes))
    response = target.raw.request(
        route.method,
        route.path(data.draw(segments)),
        params=data.draw(query_params),
        headers=data.draw(header_sets),
        content=data.draw(hostile_bodies) if route.method == "POST" else None,
    )
    _check(response.status_code, response.content, response.headers, route.method)
