"""A 3xx answer is never a success: the SDK follows no redirect, so a write that was
redirected was not carried out, and ``robocloud pin`` must not print "pinned".

The usual trigger is innocent (an http:// URL behind a proxy that redirects to https://);
a hostile service can send one as well.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from robocloud.cas import Cas
from robocloud.cli import app
from robocloud.client import RedirectError, ServiceClient
from robocloud.errors import InvalidAnswerError
from robocloud.identity import Identity
from robocloud.ledger import JsonRpcClient
from tests.scripted_http import AUDIENCE, Exchange, Reply, json_reply, scripted_server

CID = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"
runner = CliRunner()


def moved(exchange: Exchange) -> Reply:
    return 308, {"Location": f"https://cas.example.org{exchange.path}"}, b""


@pytest.mark.parametrize("status", [301, 302, 303, 307, 308])
def test_a_redirected_signed_write_is_a_redirect_error(status: int) -> None:
    def script(exchange: Exchange) -> Reply:
        return status, {"Location": "https://elsewhere.example/v1/write"}, b""

    with (
        scripted_server(script) as server,
        ServiceClient(server.url, Identity.generate(), service="cas") as client,
        pytest.raises(RedirectError) as err,
    ):
        client.post_json("/v1/write", {"x": 1})
    assert isinstance(err.value, InvalidAnswerError)
    assert (err.value.status, err.value.location) == (status, "https://elsewhere.example/v1/write")
    assert f"redirected POST /v1/write ({status}, to 'https://elsewhere.example" in str(err.value)
    assert server.count() == 1


def test_a_redirected_read_and_a_redirected_stream_are_refused(tmp_path: Path) -> None:
    with scripted_server(moved) as server, Cas(server.url) as cas:
        with pytest.raises(RedirectError):
            cas.pins()
        with pytest.raises(RedirectError):
            cas.get_to_file(CID, tmp_path / "out")
    assert list(tmp_path.iterdir()) == []


def test_a_redirected_audience_is_refused_before_signing() -> None:
    with (
        scripted_server(moved, answer_audience=False) as server,
        ServiceClient(server.url, Identity.generate()) as client,
        pytest.raises(RedirectError),
    ):
        client.post_json("/v1/write", {})
    assert [exchange.path for exchange in server.exchanges] == ["/v1/audience"]


def test_a_redirected_json_rpc_call_is_refused() -> None:
    with (
        scripted_server(moved) as server,
        JsonRpcClient(f"{server.url}/rpc") as rpc,
        pytest.raises(RedirectError),
    ):
        rpc.request("eth_chainId", [])


@pytest.mark.parametrize("command", ["pin", "unpin"])
def test_pin_says_so_in_one_line_when_it_was_redirected(command: str, keystore: Path) -> None:
    with scripted_server(moved) as server:
        result = runner.invoke(
            app, [command, CID, "--cas", server.url, "--keystore", str(keystore)]
        )
    assert result.exit_code == 6, result.output
    assert result.stdout == ""
    assert "308, to 'https://cas.example.org/api/v0/pin/" in result.stderr
    assert "ROBOCLOUD_*_URL" in result.stderr
    assert result.stderr.count("\n") == 1


def test_a_success_is_still_a_success() -> None:
    with (
        scripted_server(lambda _: json_reply(json.dumps(AUDIENCE))) as server,
        ServiceClient(server.url) as client,
    ):
        assert client.get_json("/v1/thing") == AUDIENCE
