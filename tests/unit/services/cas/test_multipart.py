"""The streaming multipart parser gives the same parts however the body is split."""

from __future__ import annotations

import pytest

from services.cas.multipart import (
    MultipartError,
    MultipartParser,
    NotMultipart,
    Part,
    PartData,
    PartEnd,
    boundary_of,
)

BOUNDARY = b"xYz-boundary"
BODY = (
    b"preamble\r\n--xYz-boundary\r\n"
    b'Content-Disposition: form-data; name="file"; filename="a.txt"\r\n'
    b"Content-Type: text/plain\r\n\r\n"
    b"first file\r\n--xYz-boundar not yet\r\n"
    b"--xYz-boundary\r\n"
    b'Content-Disposition: form-data; name="file"; filename="b.bin"\r\n\r\n'
    b"\x00\x01\x02\r\n"
    b"--xYz-boundary--\r\nepilogue"
)


def parse(body: bytes, step: int) -> list[tuple[str, bytes]]:
    parser = MultipartParser(BOUNDARY)
    files: list[tuple[str, bytes]] = []
    for start in range(0, len(body), step):
        for event in parser.feed(body[start : start + step]):
            if isinstance(event, Part):
                files.append((event.filename, b""))
            elif isinstance(event, PartData):
                name, data = files[-1]
                files[-1] = (name, data + event.data)
            else:
                assert isinstance(event, PartEnd)
    parser.close()
    return files


@pytest.mark.parametrize("step", [1, 2, 3, 7, 13, 64, len(BODY)])
def test_any_split_gives_the_same_files(step: int) -> None:
    assert parse(BODY, step) == [
        ("a.txt", b"first file\r\n--xYz-boundar not yet"),
        ("b.bin", b"\x00\x01\x02"),
    ]


@pytest.mark.parametrize("cut", [20, 120, len(BODY) - 12])
def test_a_truncated_body_raises_on_close(cut: int) -> None:
    with pytest.raises(MultipartError, match="truncated"):
        parse(BODY[:cut], 5)


def test_boundary_from_content_type() -> None:
    assert boundary_of('multipart/form-data; boundary="a b"') == b"a b"
    assert boundary_of("multipart/form-data; charset=x; boundary=abc") == b"abc"
    with pytest.raises(NotMultipart):
        boundary_of("application/json")
    with pytest.raises(MultipartError, match="boundary"):
        boundary_of("multipart/form-data")


def test_oversized_part_headers_are_refused() -> None:
    parser = MultipartParser(BOUNDARY)
    with pytest.raises(MultipartError, match="headers too large"):
        parser.feed(b"--xYz-boundary\r\nX: " + b"a" * 20_000)
