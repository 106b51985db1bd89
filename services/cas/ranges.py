"""HTTP ``Range`` for the gateway (RFC 9110 section 14): one byte range of a file.

A single range is served as 206; a header the server may ignore (several ranges, another
unit, a malformed value) gets the whole file as 200, as the RFC allows; a range wholly
outside the file is 416 with ``Content-Range: bytes */size``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

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


_ENTITY_BYTES = re.compile(r"(-?[0-9]{1,19}):(\*|-?[0-9]{1,19})")
"""RFC 9110's ASCII digits: ``\\d`` would also take ``٣`` and every other Unicode digit."""


class InvalidEntityBytes(ValueError):
    """An ``entity-bytes`` value that is malformed, or a range wholly outside the file."""

    def __init__(self, value: str, reason: str) -> None:
        super().__init__(f"entity-bytes {value[:60]!r}: {reason}")


@dataclass(frozen=True)
class EntityBytes:
    """The trustless gateway's ``entity-bytes=from:to``, parsed before the target is known.

    ``to`` is inclusive, ``None`` for ``*`` (the end); negative values count from the end.
    The value is checked whatever the path names (the specification ignores a well-formed
    range on a directory, but a malformed one is the client's mistake either way), and
    ``str`` gives its canonical text for the CAR's ``ETag``.
    """

    first: int
    last: int | None

    @classmethod
    def parse(cls, value: str) -> EntityBytes:
        """Refuses what boxo refuses: no ``from:to`` of integers or ``*``, or ``from`` after
        ``to`` when both count from the same end."""
        match = _ENTITY_BYTES.fullmatch(value)
        if match is None:
            raise InvalidEntityBytes(value, "expected from:to with integers or *")
        first = int(match.group(1))
        last = None if match.group(2) == "*" else int(match.group(2))
        if last is not None and (first < 0) == (last < 0) and first > last:
            raise InvalidEntityBytes(value, "from is after to")
        return cls(first, last)

    def __str__(self) -> str:
        return f"{self.first}:{'*' if self.last is None else self.last}"

    def within(self, size: int) -> tuple[int, int]:
        """``[start, end)`` in a file of ``size`` bytes.

        A range that is empty after clamping is ``(0, 0)`` (only the root block is sent); one
        wholly outside the file is refused, as the specification advises when it can be known
        upfront.
        """
        start = _from_start(self.first, size)
        end = size if self.last is None else _from_start(self.last, size) + 1
        if (start >= size and size > 0) or (start < 0 and end <= 0):
            raise InvalidEntityBytes(str(self), f"outside the file of {size} bytes")
        start, end = max(start, 0), min(end, size)
        return (start, end) if start < end else (0, 0)


def _from_start(offset: int, size: int) -> int:
    """An ``entity-bytes`` offset counted from the start of a file of ``size`` bytes."""
    return size + offset if offset < 0 else offset
