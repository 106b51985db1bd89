"""The services' log configuration: one JSON object a line, without the HTTP client's chatter."""

from __future__ import annotations

import json
import logging
import selectors
import subprocess
import sys
from collections.abc import Iterator

import pytest

from services.common.logs import MAX_QUEUED_LINES, configure_logging, request_id_var, stop_logging


@pytest.fixture(autouse=True)
def restored_logging() -> Iterator[None]:
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    levels = {name: logging.getLogger(name).level for name in ("httpx", "httpcore")}
    yield
    root.handlers[:] = handlers
    root.setLevel(level)
    for name, saved in levels.items():
        logging.getLogger(name).setLevel(saved)


def lines(capsys: pytest.CaptureFixture[str]) -> list[dict[str, object]]:
    stop_logging()
    return [json.loads(line) for line in capsys.readouterr().err.splitlines()]


def test_a_line_carries_the_service_the_request_id_and_the_extra_fields(
    capsys: pytest.CaptureFixture[str],
) -> None:
    configure_logging("storage")
    token = request_id_var.set("4f1c")
    try:
        logging.getLogger("robocloud.storage").info("anchored", extra={"epoch": 3})
    finally:
        request_id_var.reset(token)
    [line] = lines(capsys)
    assert (line["service"], line["request_id"], line["msg"], line["epoch"]) == (
        "storage",
        "4f1c",
        "anchored",
        3,
    )


def test_the_http_clients_request_lines_are_left_out_at_info(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A service's pollers wrote a line a second through httpx, none with a request id."""
    configure_logging("ledger", "INFO")
    logging.getLogger("httpx").info('HTTP Request: GET http://127.0.0.1:8082/v1/node "200 OK"')
    logging.getLogger("httpx").warning("a warning still shows")
    assert [line["msg"] for line in lines(capsys)] == ["a warning still shows"]


def test_the_http_clients_request_lines_show_at_debug(capsys: pytest.CaptureFixture[str]) -> None:
    configure_logging("ledger", "DEBUG")
    logging.getLogger("httpx").info("HTTP Request: GET http://127.0.0.1:8082/v1/node")
    [line] = lines(capsys)
    assert (line["logger"], line["level"]) == ("httpx", "info")


BLOCKED = """
import logging, sys, time
from services.common.logs import configure_logging
configure_logging("storage")
log = logging.getLogger("robocloud.storage")
started = time.monotonic()
for n in range(3 * {queued}):
    log.info("line %d %s", n, "x" * 1000)
print(f"logged in {{time.monotonic() - started:.1f}} s", flush=True)
"""
"""Logs three times what the queue holds, 1 KiB a line, to a stderr nobody reads before
the process says on stdout how long that took (a pipe holds 64 KiB)."""


def test_a_stderr_that_takes_nothing_never_blocks_the_service() -> None:
    """A write to a stderr nobody read (a terminal paused with Ctrl-S, a stuck supervisor)
    held the caller, on the event loop every route: past the queue's bound lines are dropped
    and counted, and the count is logged before the process exits."""
    child = subprocess.Popen(
        [sys.executable, "-c", BLOCKED.format(queued=MAX_QUEUED_LINES)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert child.stdout is not None
    try:
        with selectors.DefaultSelector() as selector:
            selector.register(child.stdout, selectors.EVENT_READ)
            assert selector.select(timeout=60), "the child is still logging: its stderr blocked it"
        said = child.stdout.readline()
        assert said.startswith("logged in "), said
        _, err = child.communicate(timeout=60)
    finally:
        child.kill()
    messages = [str(json.loads(line)["msg"]) for line in err.splitlines()]
    kept = [message for message in messages if message.startswith("line ")]
    assert kept[0].startswith("line 0 ")
    assert len(kept) >= MAX_QUEUED_LINES
    notice = f"log lines dropped: stderr took none while {MAX_QUEUED_LINES} waited"
    assert messages[-1].endswith(notice)
    assert int(messages[-1].split()[0]) + len(kept) == 3 * MAX_QUEUED_LINES
