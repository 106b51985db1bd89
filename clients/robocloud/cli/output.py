"""Output: data on stdout and nothing else; everything else on stderr.

``CID=$(robocloud put big.bin)`` captures exactly the CID because progress bars, prompts and
errors all go to stderr. With ``--json`` a command prints one JSON document instead of text.
Text is never wrapped when the stream is not a terminal, and anything a service or the chain
said goes through :func:`untrusted`, so a hostile answer cannot move the cursor, recolour the
terminal or forge extra lines.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from datetime import UTC, datetime
from typing import Any

import typer
from rich.console import Console
from rich.text import Text

UNWRAPPED_WIDTH = 1 << 20
"""Console width when not writing to a terminal: wide enough that no line is ever wrapped."""


def console(*, stderr: bool = False) -> Console:
    """A console on stdout (data) or stderr (everything else), unwrapped off a terminal.

    Built per use, so it writes to whatever ``sys.stdout``/``sys.stderr`` are at that moment.
    """
    out = Console(stderr=stderr, soft_wrap=True, highlight=False)
    if not out.is_terminal:
        out.width = UNWRAPPED_WIDTH
    return out


def show(*lines: str) -> None:
    """Print text lines on stdout as they are (no markup)."""
    out = console()
    for line in lines:
        out.print(Text(line))


def show_json(document: Any) -> None:
    """Print one JSON document on stdout (``--json``), its strings' control and format
    characters escaped: JSON escapes only those below U+0020, so a service's C1 CSI
    (U+009B), bidi override or line separator reached the terminal as they were."""
    text = json.dumps(document, ensure_ascii=False)
    if not text.isprintable():
        text = "".join(char if char.isprintable() else json.dumps(char)[1:-1] for char in text)
    typer.echo(text)


def untrusted(text: object, limit: int = 400) -> str:
    """Text a stranger wrote, safe to print on one line: control and format characters
    (escape sequences, newlines, bidi overrides) escaped, and at most ``limit`` characters."""
    value = str(text)
    if len(value) > limit:
        value = value[:limit] + "..."
    return "".join(
        char if char.isprintable() else char.encode("unicode_escape").decode() for char in value
    )


def iso8601(seconds: int) -> str:
    """A Unix time as ISO 8601 in UTC (``2025-01-31T12:00:00Z``); chain values may be absurd."""
    try:
        moment = datetime.fromtimestamp(seconds, UTC)
    except (OverflowError, OSError, ValueError):
        return f"{seconds} (not a representable time)"
    return moment.isoformat().replace("+00:00", "Z")


def size_text(size: int) -> str:
    """Bytes for people: ``1.5 GiB (1610612736 bytes)``."""
    value = float(size)
    for unit in ("KiB", "MiB", "GiB", "TiB"):
        value /= 1024
        if value < 1024:
            return f"{value:.1f} {unit} ({size} bytes)" if size >= 1024 else f"{size} bytes"
    return f"{value:.1f} PiB ({size} bytes)"


def rows(pairs: Iterable[tuple[str, object]]) -> list[str]:
    """Aligned ``label  value`` lines: the text form of one record."""
    items = list(pairs)
    width = max((len(label) for label, _ in items), default=0)
    return [f"{label.ljust(width)} {value}" for label, value in items]
