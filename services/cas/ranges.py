"""HTTP ``Range`` for the gateway (RFC 9110 section 14): one byte range of a file.

A single range is served as 206; a header the server may ignore (several ranges, another
unit, a malformed value) gets the whole file as 200, as the RFC allows; a range wholly
outside the file is 416 with ``Content-Range: bytes */size``.
"""

from __future__ import annotations

import re

from services.common.errors import RangeNotSatisfiable

_RANGE = re.compile(r"bytes=(\d*)-(\d*)")


def byte_range(header: str | None, size: int) -> tuple[int, int] | None:
    """``(start, end)`` with ``end`` exclusive, or None to serve the whole file."""
    if header is None:
        return None
    match = _RANGE.fullmatch(header.strip())
    if match is None or (not match.group(1) and not match.group(2)):
        return None
    first, last = match.group(1), match.group(2)
    if not first:
        suffix = int(last)
        if suffix == 0 or size == 0:
            raise _unsatisfiable(header, size)
        return max(0, size - suffix), size
    start = int(first)
    end = size if not last else min(int(last) + 1, size)
    if last and int(last) < start:
        return None
    if start >= size:
        raise _unsatisfiable(header, size)
    return start, end


def _unsatisfiable(header: str, size: int) -> RangeNotSatisfiable:
    return RangeNotSatisfiable(
        f"range {header!r} is outside the file of {size} bytes",
        details={"header": "Range", "size": size},
        headers={"Content-Range": f"bytes */{size}"},
    )
