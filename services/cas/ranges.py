"""HTTP ``Range`` for the gateway (RFC 9110 section 14): one byte range of a file.

A single range is served as 206; a header the server may ignore (several ranges, another
unit, a malformed value) gets the whole file as 200, as the RFC allows; a range wholly
outside the file is 416 with ``Content-Range: bytes */size``.
"""

from __future__ import annotations

import re

_RANGE = re.compile(r"bytes=(\d*)-(\d*)")
_MAX_DIGITS = 19
_BEYOND_ANY_FILE = 10**_MAX_DIGITS


def _position(digits: str) -> int:
    """A byte position; one of more than 19 digits lies beyond any file, whatever its value.

    Converting a 5,000-digit number would cost time (and CPython refuses more than 4,300
    digits), when all that matters is that it is larger than the file.
    """
    significant = digits.lstrip("0") or "0"
    return _BEYOND_ANY_FILE if len(significant) > _MAX_DIGITS else int(significant)


def _before(last: str, first: str) -> bool:
    """``last < first`` for decimal strings of any length, without converting them."""
    last, first = last.lstrip("0") or "0", first.lstrip("0") or "0"
    return (len(last), last) < (len(first), first)


def byte_range(header: str | None, size: int) -> tuple[int, int] | None:
    """``(start, end)`` with ``end`` exclusive, or None to serve the whole file."""
    if header is None:
        return None
    match = _RANGE.fullmatch(header.strip())
    if match is None or (not match.group(1) and not match.group(2)):
        return None
    first, last = match.group(1), match.group(2)
    if not first:
        suffix = _position(last)
        if suffix == 0 or size == 0:
            raise _unsatisfiable(header, size)
        return max(0, size - suffix), size
    start = _position(first)
    end = size if not last else min(_position(last) + 1, size)
    if last and _before(last, first):
        return None
    if start >= size:
        raise _unsatisfiable(header, size)
    return start, end


class UnsatisfiableRange(ValueError):
    """A range wholly outside the file; ``size`` is the file's, for ``Content-Range``."""

    def __init__(self, header: str, size: int) -> None:
        super().__init__(f"range {header!r} is outside the file of {size} bytes")
        self.size = size


def _unsatisfiable(header: str, size: int) -> UnsatisfiableRange:
    return UnsatisfiableRange(header[:100], size)
