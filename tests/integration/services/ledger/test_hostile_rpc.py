"""Unauthenticated hostile JSON-RPC bodies: each answered with a JSON-RPC error, nothing mined.

A 100,000-deep nested body used to segfault the ledger (py_ecc raises the recursion limit to
100,000, so CPython's recursive JSON decoder overflowed the C stack); ids that JSON allows but
Python cannot turn into an int, or that JSON does not allow at all, used to answer 500, and
so did a lone UTF-16 surrogate (``"\\ud800"``, valid JSON, not text) echoed in an id or a
message: it could not be encoded into the answer. Such a body is a parse error (anvil answers
-32600).
"""

from __future__ import annotations

import json
from typing import Any

import httpx
import pytest

from tests.integration.services.ledger.conftest import Service, head

CHAIN_ID_CALL = b'"jsonrpc": "2.0", "method": "eth_chainId", "params": []'


def post_rpc(service: Service, body: bytes) -> tuple[int, Any]:
    response = httpx.post(
        f"{service.url}/rpc",
        content=body,
        headers={"Content-Type": "application/json"},
        timeout=60,
    )
    return response.status_code, response.json()


@pytest.mark.parametrize(
    ("body", "code"),
    [
        (b"[" * 100_000 + b"]" * 100_000, -32600),
        (b'{"a":' * 100_000 + b"1" + b"}" * 100_000, -32600),
        (b"[" * 100_000, -32600),
        (b"{" + CHAIN_ID_CALL + b', "id": NaN}', -32600),
        (b"{" + CHAIN_ID_CALL + b', "id": ' + b"9" * 5000 + b"}", -32600),
        (b"{" + CHAIN_ID_CALL + b', "id": {"nested": 1}}', -32600),
        (b"{" + CHAIN_ID_CALL + b', "id": [1]}', -32600),
        (b"{" + CHAIN_ID_CALL + b', "id": true}', -32600),
        (b"{" + CHAIN_ID_CALL + b', "id": "' + b"x" * 1000 + b'"}', -32600),
        (b"{" + CHAIN_ID_CALL + b', "id": 1', -32700),
        (b"\xff\xfe garbage", -32700),
        (b"{" + CHAIN_ID_CALL + b', "id": "\\ud800"}', -32700),
        (b'{"jsonrpc": "2.0", "id": 1, "method": "\\udfff", "params": []}', -32700),
        (b"[{" + CHAIN_ID_CALL + b', "id": 1}, {' + CHAIN_ID_CALL + b', "id": "\\udc00"}]', -32700),
        (b'{"jsonrpc": "2.0", "id": 1, "method": "eth_getBalance", "params": ["\\ud800"]}', -32700),
    ],
    ids=[
        "nested-lists",
        "nested-objects",
        "unclosed",
        "id-nan",
        "id-5000-digits",
        "id-object",
        "id-array",
        "id-bool",
        "id-long-string",
        "truncated",
        "not-utf8",
        "id-lone-surrogate",
        "method-lone-surrogate",
        "batch-lone-surrogate",
        "param-lone-surrogate",
    ],
)
def test_hostile_bodies_get_json_rpc_errors_and_change_nothing(
    service: Service, body: bytes, code: int
) -> None:
    before = head(service.url)
    status, answer = post_rpc(service, body)
    assert status == 200
    assert answer["jsonrpc"] == "2.0"
    assert answer["id"] is None
    assert answer["error"]["code"] == code, answer
    assert head(service.url) == before
    assert service.process.process is not None
    assert service.process.process.poll() is None
    status, answer = post_rpc(service, b"{" + CHAIN_ID_CALL + b', "id": 7}')
    assert (status, answer) == (200, {"jsonrpc": "2.0", "id": 7, "result": "0x539"})


@pytest.mark.parametrize("request_id", ["7", "abc", 1.5, None, 10**100])
def test_every_valid_id_is_echoed(service: Service, request_id: Any) -> None:
    payload = {"jsonrpc": "2.0", "id": request_id, "method": "eth_chainId", "params": []}
    answer = httpx.post(f"{service.url}/rpc", json=payload, timeout=30).json()
    assert answer == {"jsonrpc": "2.0", "id": request_id, "result": "0x539"}


@pytest.mark.parametrize(
    "method",
    [["eth_call"], {"name": "eth_chainId"}, 7, None],
    ids=["list", "object", "number", "null"],
)
def test_a_method_that_is_not_a_string_is_an_invalid_request(service: Service, method: Any) -> None:
    """A list as the method used to answer 500: the inline path looked it up in a dict."""
    before = head(service.url)
    payload = {"jsonrpc": "2.0", "id": 1, "method": method, "params": []}
    status, answer = post_rpc(service, json.dumps(payload).encode())
    assert (status, answer) == (
        200,
        {
            "jsonrpc": "2.0",
            "id": 1,
            "error": {"code": -32600, "message": "method must be a string, params an array"},
        },
    )
    assert head(service.url) == before
