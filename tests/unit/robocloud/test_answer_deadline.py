"""How long a slow service can hold a robot: an answer read whole has a deadline, a streamed
body a lowest speed, and an ingest job is followed for a bounded time.

httpx's timeout bounds each read, so a server dripping one byte just inside it would
otherwise hold a client for as long as it likes (64 MiB at a byte per 29 s is 60 years).
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler
from pathlib import Path

import httpx
import pytest
from typer.testing import CliRunner

from robocloud.cas import Cas
from robocloud.cli import app
from robocloud.client import AnswerDeadlineError, ServiceClient
from robocloud.deadline import LowSpeed, LowSpeedGuard
from robocloud.errors import TransportTimeoutError
from robocloud.ingest import Ingest
from tests.scripted_http import Exchange, Reply, json_reply, scripted_server, serving
from tests.unit.robocloud.test_ingest_answers import JOB

BODY = b'{"Keys": {}, "padding": "' + b"x" * 40 + b'"}'
runner = CliRunner()


HEAD = (
    b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\n"
    + f"Content-Length: {len(BODY)}\r\n\r\n".encode()
)


@dataclass
class Dripping:
    url: str
    paths: list[str] = field(default_factory=list)
    sent: int = 0
    """Bytes of the current answer written so far (status line and headers included)."""


@contextmanager
def dripping_server(pause_s: float, *, headers_too: bool = False) -> Iterator[Dripping]:
    """A server that answers every request with ``BODY``, one byte every ``pause_s``; with
    ``headers_too``, its status line and headers as well."""
    state = Dripping("")

    class Drip(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.do_POST()

        def do_POST(self) -> None:
            state.paths.append(self.path)
            self.rfile.read(int(self.headers.get("Content-Length") or 0))
            answer, state.sent = HEAD + BODY, 0
            if not headers_too:
                self.wfile.write(HEAD)
                state.sent = len(HEAD)
            try:
                while state.sent < len(answer):
                    self.wfile.write(answer[state.sent : state.sent + 1])
                    self.wfile.flush()
                    state.sent += 1
                    time.sleep(pause_s)
            except OSError:
                return

        def log_message(self, *args: object) -> None:
            return None

    with serving(Drip) as state.url:
        yield state


def test_a_dripped_answer_ends_at_the_deadline_and_is_not_retried() -> None:
    with dripping_server(0.3) as server, Cas(server.url, timeout=0.5, backoff_s=0.01) as cas:
        started = time.monotonic()
        with pytest.raises(AnswerDeadlineError, match="not complete 2 s after the request"):
            cas.pins()
        elapsed = time.monotonic() - started
    # The whole answer takes 21 s; a margin wide enough for a loaded machine still tells.
    assert 2.0 <= elapsed < 10.0
    assert server.paths == ["/api/v0/pin/ls"]


def test_the_deadline_is_the_clients_to_choose() -> None:
    with (
        dripping_server(0.02) as server,
        ServiceClient(server.url, timeout=0.5, answer_deadline_s=30) as client,
    ):
        assert client.get_json("/slow-but-steady")["Keys"] == {}
    with (
        dripping_server(0.3) as server,
        ServiceClient(server.url, timeout=5, answer_deadline_s=0.5, retries=0) as client,
    ):
        started = time.monotonic()
        with pytest.raises(AnswerDeadlineError):
            client.get_json("/x")
        assert time.monotonic() - started < 10.0  # the whole answer takes 21 s


def test_dripped_headers_end_at_the_deadline_and_are_not_retried() -> None:
    """The deadline used to start once the headers were in: a service dripping its status
    line and headers (71 bytes here, 21 s; up to h11's 100 KiB cap in all) held the
    robot for as long as that took, a byte per read timeout: it gave up only once they were
    all in."""
    with (
        dripping_server(0.3, headers_too=True) as server,
        Cas(server.url, timeout=0.5, backoff_s=0.01) as cas,
    ):
        with pytest.raises(AnswerDeadlineError, match="not complete 2 s after the request"):
            cas.pins()
        assert server.sent < len(HEAD)
    assert server.paths == ["/api/v0/pin/ls"]


def test_a_streamed_answers_headers_have_the_deadline() -> None:
    with (
        dripping_server(0.3, headers_too=True) as server,
        ServiceClient(server.url, timeout=5, answer_deadline_s=1, retries=0) as client,
    ):
        with pytest.raises(AnswerDeadlineError, match="not complete 1 s after the request"):
            client.send("GET", "/stream", stream=True)
        assert server.sent < len(HEAD)
    assert server.paths == ["/stream"]


def test_a_streamed_body_too_slow_is_ended_and_leaves_the_old_file(tmp_path: Path) -> None:
    """A streamed body had only the per-read timeout, so a service dripping a byte just inside
    it held an export for as long as the body was long (a GiB: a thousand years at a byte
    per 29 s), and what had come was left under the export's name as if it were all."""
    out = tmp_path / "run.mcap"
    out.write_bytes(b"the previous export\n")
    slowest = LowSpeed(min_bytes=64, window_s=1.0)
    with (
        dripping_server(0.2) as server,
        Ingest(server.url, timeout=5, retries=0, low_speed=slowest) as ingest,
    ):
        started = time.monotonic()
        with pytest.raises(
            TransportTimeoutError, match=r"came too slowly: \d+ bytes in \d+ s, under 64 in 1 s"
        ):
            ingest.export({"template": "imu@1", "format": "mcap"}, out)
        elapsed = time.monotonic() - started
    assert elapsed < 8.0  # the whole body takes 15 s
    assert server.paths[0].startswith("/v1/export?")
    assert out.read_bytes() == b"the previous export\n"
    assert [path.name for path in tmp_path.iterdir()] == ["run.mcap"]


def test_a_steady_stream_is_read_whole(tmp_path: Path) -> None:
    out = tmp_path / "run.jsonl"
    with (
        dripping_server(0.005) as server,
        Ingest(server.url, low_speed=LowSpeed(min_bytes=8, window_s=0.2)) as ingest,
    ):
        assert ingest.export({"template": "imu@1", "format": "jsonl"}, out) == len(BODY)
    assert out.read_bytes() == BODY


class Chunks(httpx.SyncByteStream):
    def __init__(self, *chunks: bytes) -> None:
        self.chunks = chunks
        self.closed = False

    def __iter__(self) -> Iterator[bytes]:
        yield from self.chunks

    def close(self) -> None:
        self.closed = True


def test_each_window_needs_its_own_bytes() -> None:
    """Enough bytes in one window do not carry over to the next."""
    body = Chunks(b"x" * 5, b"x" * 5, b"x" * 3, b"x" * 3)
    times = iter([0.0, 0.5, 1.0, 1.5, 2.5])
    guard = LowSpeedGuard(body, LowSpeed(min_bytes=10, window_s=1.0), clock=lambda: next(times))
    read: list[bytes] = []
    with pytest.raises(httpx.ReadTimeout, match="6 bytes in 2 s, under 10 in 1 s"):
        read.extend(guard)
    assert [len(chunk) for chunk in read] == [5, 5, 3]
    guard.close()
    assert body.closed


def test_a_slow_upload_is_not_the_answers_time() -> None:
    """A robot sending its body slowly (a bag read off a slow disk, a thin uplink) used to
    have that time counted against the answer, and a prompt answer to a 4 s upload failed
    a 2 s deadline after the service had done the work."""
    chunks = [b"x" * 1000] * 8

    def slowly() -> Iterator[bytes]:
        for chunk in chunks:
            time.sleep(0.5)
            yield chunk

    with (
        scripted_server(
            lambda exchange: json_reply(json.dumps({"got": len(exchange.body)}))
        ) as server,
        ServiceClient(server.url, timeout=5, answer_deadline_s=2, retries=0) as client,
    ):
        response = client.send(
            "POST",
            "/upload",
            content=slowly(),
            headers={"Content-Length": "8000"},
            signed=False,
        )
    assert response.status_code == 200
    assert client.json_of(response) == {"got": 8000}
    assert [exchange.path for exchange in server.exchanges] == ["/upload"]


def running_job(exchange: Exchange) -> Reply:
    job = {**JOB, "status": "running", "messages": {"done": 1, "total": 10}}
    return json_reply(json.dumps(job))


def test_waiting_for_a_job_that_never_ends_is_bounded() -> None:
    """Without the bound it polls forever (pytest's timeout ends it as a failure)."""
    with scripted_server(running_job) as server, Ingest(server.url) as ingest:
        job = ingest.wait("j1", poll_s=0.05, timeout_s=0.5)
    assert job["status"] == "running"


def test_the_cli_gives_up_on_a_job_that_never_ends_in_one_line(
    keystore: Path, tmp_path: Path
) -> None:
    bag = tmp_path / "x.mcap"
    bag.write_bytes(b"\x89MCAP0\r\n" + bytes(64))
    with scripted_server(running_job) as server:
        command = ["ingest", str(bag), "--storage", server.url, "--keystore", str(keystore)]
        result = runner.invoke(app, [*command, "--timeout", "0.5"])
    assert result.exit_code == 5, result.output
    assert result.stderr.startswith("error: ingest job j1 is still running after 0.5 s")
    assert result.stderr.count("\n") == 1


def test_a_robot_behind_a_proxy_still_goes_through_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """httpx reads no proxy from the environment for a client given its own transport, as the
    SDK's clients now are; the SDK picks the proxy itself, as httpx did."""
    monkeypatch.delenv("no_proxy", raising=False)
    monkeypatch.delenv("NO_PROXY", raising=False)
    with scripted_server(lambda exchange: json_reply('{"via": "proxy"}')) as proxy:
        monkeypatch.setenv("http_proxy", proxy.url)
        with ServiceClient("http://robocloud.invalid:8080", timeout=5, retries=0) as client:
            assert client.get_json("/v1/thing") == {"via": "proxy"}
    assert [exchange.path for exchange in proxy.exchanges] == [
        "http://robocloud.invalid:8080/v1/thing"
    ]


def test_no_proxy_names_the_hosts_reached_directly(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("http_proxy", "http://127.0.0.1:9")
    monkeypatch.setenv("no_proxy", "127.0.0.1")
    with (
        scripted_server(lambda exchange: json_reply('{"via": "direct"}')) as server,
        ServiceClient(server.url, timeout=5, retries=0) as client,
    ):
        assert client.get_json("/v1/thing") == {"via": "direct"}
    assert [exchange.path for exchange in server.exchanges] == ["/v1/thing"]
