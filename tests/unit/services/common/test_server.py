"""The request-head meter: limits found as the bytes arrive, however the head is split."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from services.common.server import HeadMeter, Refusal
from services.common.settings import ServiceSettings

HEAD = b"GET /ipfs/bafy HTTP/1.1\r\nHost: cas\r\nX-Thing: value\r\n\r\n"


def feed_all(meter: HeadMeter, chunks: list[bytes]) -> Refusal | None:
    for chunk in chunks:
        refusal = meter.feed(chunk)
        if refusal is not None:
            return refusal
    return None


@pytest.mark.parametrize("size", [1, 2, 3, 7, len(HEAD)])
def test_a_head_within_the_limits_passes_however_it_is_split(size: int) -> None:
    meter = HeadMeter(max_request_line_bytes=64, max_header_bytes=len(HEAD))
    chunks = [HEAD[i : i + size] for i in range(0, len(HEAD), size)]
    assert feed_all(meter, chunks) is None
    assert not meter.counting, "the blank line ended the head, even split across chunks"


def test_body_bytes_after_the_head_do_not_count() -> None:
    meter = HeadMeter(max_request_line_bytes=64, max_header_bytes=len(HEAD))
    assert meter.feed(HEAD + b"b" * 1_000_000) is None
    assert meter.feed(b"more body" * 1000) is None


def test_a_bare_lf_head_ends_where_h11_ends_it() -> None:
    meter = HeadMeter(max_request_line_bytes=64, max_header_bytes=100)
    assert meter.feed(b"GET / HTTP/1.1\nHost: x\n\n" + b"x" * 500) is None
    assert not meter.counting


def test_long_request_line_is_414_before_its_end_arrives() -> None:
    meter = HeadMeter(max_request_line_bytes=100, max_header_bytes=10_000)
    assert meter.feed(b"GET /" + b"a" * 90) is None
    refusal = meter.feed(b"a" * 10)
    assert refusal == Refusal(
        414, "request_line_too_long", "the request line exceeds 100 bytes", {"limit": 100}
    )


def test_long_header_field_is_431_before_the_head_ends() -> None:
    meter = HeadMeter(max_request_line_bytes=100, max_header_bytes=1000)
    assert meter.feed(b"GET / HTTP/1.1\r\nX-Big: ") is None  # 23 bytes
    refusals = [meter.feed(b"a" * 100) for _ in range(10)]
    assert refusals[:9] == [None] * 9, "923 bytes so far"
    refusal = refusals[9]
    assert refusal is not None
    assert (refusal.status, refusal.code, refusal.details) == (
        431,
        "headers_too_large",
        {"limit": 1000},
    )


def test_a_complete_head_over_the_limit_in_one_chunk_is_431() -> None:
    meter = HeadMeter(max_request_line_bytes=100, max_header_bytes=len(HEAD) - 1)
    refusal = meter.feed(HEAD)
    assert refusal is not None
    assert refusal.status == 431


def test_byte_at_a_time_counts_every_byte() -> None:
    meter = HeadMeter(max_request_line_bytes=100, max_header_bytes=500)
    head = b"GET / HTTP/1.1\r\n" + b"X: " + b"v" * 1000
    refusal = feed_all(meter, [head[i : i + 1] for i in range(len(head))])
    assert refusal is not None
    assert refusal.status == 431


def test_start_counts_the_next_request_afresh() -> None:
    meter = HeadMeter(max_request_line_bytes=64, max_header_bytes=len(HEAD))
    assert meter.feed(HEAD) is None
    meter.start()
    assert meter.counting
    assert meter.feed(HEAD) is None
    meter.start()
    refusal = meter.feed(HEAD[:-2] + b"X: y\r\n\r\n")
    assert refusal is not None
    assert refusal.status == 431


def test_limits_are_settings_with_documented_defaults() -> None:
    settings = ServiceSettings()
    assert (settings.max_request_line_bytes, settings.max_header_bytes) == (8192, 65536)
    with pytest.raises(ValidationError, match="max_request_line_bytes"):
        ServiceSettings(max_request_line_bytes=10_000, max_header_bytes=9_000)
