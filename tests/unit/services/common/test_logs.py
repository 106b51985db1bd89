"""The services' log configuration: one JSON object a line, without the HTTP client's chatter."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator

import pytest

from services.common.logs import configure_logging, request_id_var


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
