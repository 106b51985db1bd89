"""CARv1: the transport of DAGs between robocloud and the IPFS ecosystem.

A CAR is a varint-framed dag-cbor header ``{"roots": [...], "version": 1}`` followed by
varint-framed ``(CID, block)`` sections. The reader verifies every block against its CID as
it streams past, so a CAR from anywhere can be trusted block by block.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Protocol

from robocloud.cid import CID, Block, CIDError, encode_varint
from robocloud.errors import FormatError

MAX_HEADER_BYTES = 1 << 20
MAX_HEADER_DEPTH = 8
"""A CARv1 header nests three levels (map, roots list, CID tag); more is not a CAR header."""
MAX_ROOTS = 1024
MAX_SECTION_BYTES = 8 << 20
CID_TAG = 42


class ByteSource(Protocol):
    """Anything with ``read(size)``: an open file, a socket file, a streamed HTTP body."""

    def read(self, size: int = -1, /) -> bytes: ...


class CarError(FormatError):
    """A CAR that is malformed or carries a block that does not match its CID."""


def _cbor_head(major: int, value: int) -> bytes:
    if value < 24:
        return bytes([major << 5 | value])
    for info, width in ((24, 1), (25, 2), (26, 4), (27, 8)):
        if value < 1 << (8 * width):
            return bytes([major << 5 | info]) + value.to_bytes(width, "big")
    raise CarError("CBOR length too large")


def encode_header(roots: list[CID]) -> bytes:
    """dag-cbor of ``{"roots": [...], "version": 1}``: keys in dag-cbor order (length first)."""
    body = _cbor_head(5, 2) + _cbor_head(3, 5) + b"roots" + _cbor_head(4, len(roots))
    for root in roots:
        binary = b"\x00" + root.binary
        body += _cbor_head(6, CID_TAG) + _cbor_head(2, len(binary)) + binary
    body += _cbor_head(3, 7) + b"version" + _cbor_head(0, 1)
    return body


def write_car(roots: list[CID], blocks: Iterable[Block]) -> Iterator[bytes]:
    """Stream a CARv1: the header, then one section per block."""
    header = encode_header(roots)
    yield encode_varint(len(header)) + header
    for cid, data in blocks:
        binary = cid.binary
        yield encode_varint(len(binary) + len(data)) + binary
        yield data


class _Cbor:
    """Just enough of a CBOR decoder for CAR headers (maps, arrays, text, bytes, tags, uints)."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def _head(self) -> tuple[int, int]:
        if self.pos >= len(self.data):
            raise CarError("truncated CAR header")
        first = self.data[self.pos]
        self.pos += 1
        major, info = first >> 5, first & 0x1F
        if info < 24:
            return major, info
        width = {24: 1, 25: 2, 26: 4, 27: 8}.get(info)
        if width is None:
            raise CarError("indefinite or reserved CBOR lengths are not dag-cbor")
        value = int.from_bytes(self.data[self.pos : self.pos + width], "big")
        self.pos += width
        return major, value

    def _key(self, depth: int) -> str:
        key = self.item(depth)
        if not isinstance(key, str):
            raise CarError("dag-cbor map keys must be strings")
        return key

    def item(self, depth: int = 0) -> object:
        """The next item; containers recurse at most ``MAX_HEADER_DEPTH`` levels."""
        if depth > MAX_HEADER_DEPTH:
            raise CarError(f"CAR header nested deeper than {MAX_HEADER_DEPTH} levels")
        major, value = self._head()
        if major == 0:
            return value
        if major in (2, 3):
            raw = self.data[self.pos : self.pos + value]
            if len(raw) != value:
                raise CarError("truncated CAR header")
            self.pos += value
            if major == 2:
                return raw
            try:
                return raw.decode()
            except UnicodeDecodeError as exc:
                raise CarError(f"a CAR header string that is not UTF-8: {exc}") from exc
        if major == 4:
            return [self.item(depth + 1) for _ in range(value)]
        if major == 5:
            return {self._key(depth + 1): self.item(depth + 1) for _ in range(value)}
        if major == 6 and value == CID_TAG:
            tagged = self.item(depth + 1)
            if not isinstance(tagged, bytes) or tagged[:1] != b"\x00":
                raise CarError("CID tag without a multibase-identity byte string")
            return CID.from_bytes(tagged[1:])
        raise CarError(f"unexpected CBOR major type {major} in a CAR header")


def _read_varint(stream: ByteSource) -> int | None:
    """A varint from the stream; ``None`` at a clean end of stream."""
    value = shift = 0
    for index in range(10):
        byte = stream.read(1)
        if not byte:
            if index == 0:
                return None
            raise CarError("truncated varint in CAR")
        value |= (byte[0] & 0x7F) << shift
        if not byte[0] & 0x80:
            return value
        shift += 7
    raise CarError("oversized varint in CAR")


def _read_exactly(stream: ByteSource, size: int) -> bytes:
    data = stream.read(size)
    if len(data) != size:
        raise CarError(f"truncated CAR: wanted {size} bytes, got {len(data)}")
    return data


class CarReader:
    """Iterate the verified blocks of a CARv1 stream; ``roots`` is read at construction."""

    def __init__(self, stream: ByteSource, *, max_section: int = MAX_SECTION_BYTES) -> None:
        self.stream = stream
        self.max_section = max_section
        size = _read_varint(stream)
        if size is None or size == 0 or size > MAX_HEADER_BYTES:
            raise CarError("missing or oversized CAR header")
        try:
            header = _Cbor(_read_exactly(stream, size)).item()
        except CIDError as exc:
            raise CarError(f"invalid root in CAR header: {exc}") from exc
        if not isinstance(header, dict) or header.get("version") != 1:
            raise CarError("not a CARv1 header (version must be 1)")
        roots = header.get("roots")
        if not isinstance(roots, list) or not all(isinstance(r, CID) for r in roots):
            raise CarError("CAR header roots must be a list of CIDs")
        if len(roots) > MAX_ROOTS:
            raise CarError(f"a CAR header with {len(roots)} roots, more than {MAX_ROOTS}")
        self.roots: list[CID] = roots

    def __iter__(self) -> Iterator[Block]:
        while True:
            size = _read_varint(self.stream)
            if size is None:
                return
            if size > self.max_section:
                raise CarError(f"CAR section of {size} bytes exceeds {self.max_section}")
            section = _read_exactly(self.stream, size)
            try:
                cid, start = CID.read(section, 0)
                cid.verify(memoryview(section)[start:])
            except CIDError as exc:
                raise CarError(f"bad block in CAR: {exc}") from exc
            yield Block(cid, section[start:])
