"""What the CLI prints: untrusted text neutralised, times in ISO 8601, sizes parsed."""

from __future__ import annotations

import pytest
import typer

from robocloud.cli.context import parse_size
from robocloud.cli.output import iso8601, rows, size_text, untrusted


@pytest.mark.parametrize(
    ("text", "shown"),
    [
        ("plain text", "plain text"),
        ("two\nlines", "two\\nlines"),
        ("\x1b[2J\x1b[31mred", "\\x1b[2J\\x1b[31mred"),
        ("evil\u202eafter", "evil\\u202eafter"),
        ("tab\there\r", "tab\\there\\r"),
        ("ünïcödé ✓", "ünïcödé ✓"),
    ],
)
def test_untrusted_text_is_one_inert_line(text: str, shown: str) -> None:
    assert untrusted(text) == shown


def test_untrusted_text_is_bounded() -> None:
    assert untrusted("x" * 10_000, 50) == "x" * 50 + "..."


@pytest.mark.parametrize(
    ("seconds", "shown"),
    [
        (0, "1970-01-01T00:00:00Z"),
        (1_700_000_000, "2023-11-14T22:13:20Z"),
        (2**255, f"{2**255} (not a representable time)"),
    ],
)
def test_times_are_iso_8601_in_utc(seconds: int, shown: str) -> None:
    assert iso8601(seconds) == shown


@pytest.mark.parametrize(
    ("text", "size"),
    [("1048576", 1 << 20), ("10MB", 10**7), ("2GiB", 2 << 30), ("5 kib", 5120), ("0", 0)],
)
def test_sizes_parse(text: str, size: int) -> None:
    assert parse_size(text) == size


@pytest.mark.parametrize("text", ["", "-1", "1.5GB", "ten", "1XB", "9" * 100])
def test_bad_sizes_are_usage_errors(text: str) -> None:
    with pytest.raises(typer.BadParameter, match="is not a size"):
        parse_size(text)


def test_sizes_and_rows_read_well() -> None:
    assert size_text(512) == "512 bytes"
    assert size_text(3 << 30) == "3.0 GiB (3221225472 bytes)"
    assert rows([("state", "active"), ("registered", "x")]) == [
        "state      active",
        "registered x",
    ]
