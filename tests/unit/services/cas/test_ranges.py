"""Range headers as RFC 9110 reads them."""

from __future__ import annotations

import pytest

from services.cas.errors import ERRORS
from services.cas.ranges import UnsatisfiableRange, byte_range


@pytest.mark.parametrize(
    ("header", "expected"),
    [
        (None, None),
        ("bytes=0-9", (0, 10)),
        ("bytes=5-", (5, 100)),
        ("bytes=-5", (95, 100)),
        ("bytes=-500", (0, 100)),
        ("bytes=90-500", (90, 100)),
        ("bytes=0-1,4-5", None),
        ("items=0-1", None),
        ("bytes=9-1", None),
        ("bytes=-", None),
        ("bytes=0-" + "9" * 5000, (0, 100)),
        ("bytes=-" + "9" * 5000, (0, 100)),
        ("bytes=" + "0" * 5000 + "7-8", (7, 9)),
        ("bytes=" + "9" * 5000 + "-" + "1" * 5000, None),
    ],
)
def test_served_ranges(header: str | None, expected: tuple[int, int] | None) -> None:
    assert byte_range(header, 100) == expected


@pytest.mark.parametrize(
    ("header", "size"),
    [("bytes=100-", 100), ("bytes=-0", 100), ("bytes=0-", 0), ("bytes=" + "9" * 5000 + "-", 100)],
)
def test_unsatisfiable(header: str, size: int) -> None:
    with pytest.raises(UnsatisfiableRange) as exc:
        byte_range(header, size)
    assert exc.value.size == size
    error = ERRORS.to_service_error(exc.value)
    assert error is not None
    assert (error.status, error.code) == (416, "range_not_satisfiable")
    assert error.headers == {"Content-Range": f"bytes */{size}"}
    assert len(error.message) < 200
