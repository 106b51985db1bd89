"""A push parser for multipart/form-data bodies, the way kubo's RPC receives files.

Uploads are fed chunk by chunk as they arrive and file bytes are passed on at once, so a
gigabyte upload never sits in memory. Scanning uses ``bytes.find`` for the delimiter, which
keeps the parser far faster than the network (python-multipart steps through part data in
Python and would cap uploads well below the speed this gateway promises).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from urllib.parse import unquote_plus

MAX_HEADER_BYTES = 16 * 1024
_BOUNDARY = re.compile(r'boundary=(?:"([^"]{1,70})"|([^\s;,]{1,70}))', re.IGNORECASE)
_PARAM = re.compile(r'(\w+)\*?=(?:"((?:[^"\\]|\\.)*)"|([^;\s]+))')


@dataclass
class Part:
    """A part's headers (lower-cased names) and what its Content-Disposition says."""

    headers: dict[str, str]

    @property
    def content_type(self) -> str:
        return self.headers.get("content-type", "application/octet-stream").split(";")[0].strip()

    def disposition(self, key: str) -> str | None:
        for match in _PARAM.finditer(self.headers.get("content-disposition", "")):
            if match.group(1).lower() == key:
                return match.group(2) if match.group(2) is not None else match.group(3)
        return None

    @property
    def filename(self) -> str:
        """The part's path, unescaped as kubo does (Go's ``url.QueryUnescape``)."""
        raw = self.disposition("filename") or self.disposition("name") or ""
        return query_unescape(raw)

    @property
    def is_directory(self) -> bool:
        return self.content_type == "application/x-directory"


_BAD_ESCAPE = re.compile(r"%(?![0-9A-Fa-f]{2})")


def query_unescape(text: str) -> str:
    """``+`` is a space and ``%XX`` a byte of UTF-8; a malformed escape is an error, as in Go."""
    if _BAD_ESCAPE.search(text):
        raise MultipartError(f"the part name {text[:80]!r} has a malformed %-escape")
    try:
        return unquote_plus(text, errors="strict")
    except UnicodeDecodeError as exc:
        raise MultipartError(f"the part name {text[:80]!r} is not UTF-8 once unescaped") from exc


@dataclass
class PartData:
    data: bytes


@dataclass
class PartEnd:
    pass


Event = Part | PartData | PartEnd


class NotMultipart(ValueError):
    """The body is not declared ``multipart/form-data``."""

    def __init__(self, content_type: str | None) -> None:
        super().__init__("the body must be multipart/form-data")
        self.content_type = content_type


class MultipartError(ValueError):
    """Malformed multipart framing; ``header`` names the request header at fault, if one is."""

    def __init__(self, message: str, header: str | None = None) -> None:
        super().__init__(message)
        self.header = header


class TruncatedMultipart(MultipartError):
    def __init__(self) -> None:
        super().__init__(
            "the multipart body is truncated: its closing boundary is missing; nothing was stored"
        )


def boundary_of(content_type: str | None) -> bytes:
    """The boundary of a multipart/form-data Content-Type."""
    media = (content_type or "").split(";", 1)[0].strip().lower()
    if media != "multipart/form-data":
        raise NotMultipart(content_type)
    match = _BOUNDARY.search(content_type or "")
    if match is None:
        raise MultipartError("multipart/form-data without a boundary", header="Content-Type")
    return (match.group(1) or match.group(2)).encode("latin-1")


class MultipartParser:
    """Feed body chunks, get events; ``close`` raises if the body ended mid-way."""

    def __init__(self, boundary: bytes) -> None:
        self._first = b"--" + boundary
        self._delimiter = b"\r\n--" + boundary
        self._buffer = bytearray()
        self._state = "preamble"

    def feed(self, data: bytes) -> list[Event]:
        self._buffer += data
        events: list[Event] = []
        while self._step(events):
            pass
        return events

    def close(self) -> None:
        if self._state != "done":
            raise TruncatedMultipart()

    def _step(self, events: list[Event]) -> bool:
        if self._state == "preamble":
            return self._preamble()
        if self._state == "after_boundary":
            return self._after_boundary()
        if self._state == "headers":
            return self._headers(events)
        if self._state == "data":
            return self._data(events)
        self._buffer.clear()
        return False

    def _preamble(self) -> bool:
        at = self._buffer.find(self._first)
        if at < 0:
            if len(self._buffer) > MAX_HEADER_BYTES:
                raise MultipartError("no multipart boundary found")
            return False
        del self._buffer[: at + len(self._first)]
        self._state = "after_boundary"
        return True

    def _after_boundary(self) -> bool:
        if len(self._buffer) < 2:
            return False
        marker = bytes(self._buffer[:2])
        del self._buffer[:2]
        if marker == b"--":
            self._state = "done"
        elif marker == b"\r\n":
            self._state = "headers"
        else:
            raise MultipartError("malformed multipart boundary line")
        return True

    def _headers(self, events: list[Event]) -> bool:
        end = self._buffer.find(b"\r\n\r\n")
        if end < 0:
            if len(self._buffer) > MAX_HEADER_BYTES:
                raise MultipartError("multipart part headers too large")
            return False
        headers: dict[str, str] = {}
        for line in bytes(self._buffer[:end]).decode("utf-8", "replace").split("\r\n"):
            name, colon, value = line.partition(":")
            if not colon:
                raise MultipartError(f"malformed part header {line!r}")
            headers[name.strip().lower()] = value.strip()
        del self._buffer[: end + 4]
        events.append(Part(headers))
        self._state = "data"
        return True

    def _data(self, events: list[Event]) -> bool:
        at = self._buffer.find(self._delimiter)
        if at < 0:
            keep = len(self._delimiter) - 1
            if len(self._buffer) > keep:
                events.append(PartData(bytes(self._buffer[:-keep])))
                del self._buffer[:-keep]
            return False
        if at:
            events.append(PartData(bytes(self._buffer[:at])))
        del self._buffer[: at + len(self._delimiter)]
        events.append(PartEnd())
        self._state = "after_boundary"
        return True
