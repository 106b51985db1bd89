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


_ENTITY_BYTES = re.compile(r"(-?\d{1,19}):(\*|-?\d{1,19})")


class InvalidEntityBytes(ValueError):
    """An ``entity-bytes`` value that is malformed, or a range wholly outside the file."""

    def __init__(self, value: str, reason: str) -> None:
        super().__init__(f"entity-bytes {value[:60]!r}: {reason}")


def entity_bytes(value: str, size: int) -> tuple[int, int]:
    """``[start, end)`` of the trustless gateway's ``entity-bytes=from:to`` for a file of ``size``.

    ``to`` is inclusive or ``*`` (the end); negative values count from the end. A range that
    is empty after clamping is ``(0, 0)`` (only the root block is sent); one wholly outside
    the file is refused, as the specification advises when it can be known upfront.
    """
    match = _ENTITY_BYTES.fullmatch(value)
    if match is None:
        raise InvalidEntityBytes(value, "expected from:to with integers or *")
    first = int(match.group(1))
    start = size + first if first < 0 else first
    last = match.group(2)
    end = (
        size if last == "*" else (size + int(last) if int(last) < 0 else int(last)) + (last != "*")
    )
    if (start >= size and size > 0) or (start < 0 and end <= 0):
        raise InvalidEntityBytes(value, f"outside the file of {size} bytes")
    start, end = max(start, 0), min(end, size)
    return (start, end) if start < end else (0, 0)
