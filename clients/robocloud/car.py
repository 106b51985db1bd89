"""CARv1: the transport of DAGs between robocloud and the IPFS ecosystem.

A CAR is a varint-framed dag-cbor header ``{"roots": [...], "version": 1}`` followed by
varint-framed ``(CID, block)`` sections. The reader verifies every block against its CID as
it streams past, so a CAR from anywhere can be trusted block by block.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Protocol

from robocloud.cid import CID, MAX_VARINT_BYTES, Block, CIDError, encode_varint
from robocloud.errors import FormatError

MAX_HEADER_BYTES = 1 << 20
"""Generous: 1,024 roots of the largest CID this SDK reads (identity, 128 bytes) take 140 KiB."""
MAX_HEADER_DEPTH = 8
"""A CARv1 header nests three levels (map, roots list, CID tag); more is not a CAR header."""
MAX_ROOTS = 1024
MAX_SECTION_BYTES = 8 << 20
"""go-car's default section limit: a block and its CID (bitswap moves blocks up to 2 MiB)."""
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
    """Just enough of a CBOR decoder for CAR headers (maps, arrays, text, bytes, tags, uints).

    Bounded by construction: the header's size is bounded before it is read, containers nest
    at most ``MAX_HEADER_DEPTH`` levels (the recursion is that deep at most), and no
    container may claim more items than ``MAX_ROOTS`` or than there are bytes left, so a
    count of 2^64 is refused before a single item is read.
    """

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def _head(self) -> tuple[int, int, int]:
        """``(major type, argument, offset of the item)``."""
        at = self.pos
        if at >= len(self.data):
            raise CarError(f"truncated CAR header: an item is missing at byte {at}")
        first = self.data[at]
        major, info = first >> 5, first & 0x1F
        if info < 24:
            self.pos = at + 1
            return major, info, at
        width = {24: 1, 25: 2, 26: 4, 27: 8}.get(info)
        if width is None:
            raise CarError(
                f"CAR header byte {at}: indefinite or reserved CBOR lengths are not dag-cbor"
            )
        if at + 1 + width > len(self.data):
            raise CarError(f"truncated CAR header: the CBOR argument at byte {at}")
        self.pos = at + 1 + width
        return major, int.from_bytes(self.data[at + 1 : self.pos], "big"), at

    def _count(self, count: int, at: int) -> int:
        if count > MAX_ROOTS:
            raise CarError(
                f"CAR header byte {at}: a CBOR container of {count} items, more than "
                f"{MAX_ROOTS} (the most roots a header may hold)"
            )
        if count > len(self.data) - self.pos:
            raise CarError(
                f"truncated CAR header: {count} items at byte {at}, "
                f"{len(self.data) - self.pos} bytes left"
            )
        return count

    def item(self, depth: int = 0) -> object:
        """The next item; containers recurse at most ``MAX_HEADER_DEPTH`` levels."""
        if depth > MAX_HEADER_DEPTH:
            raise CarError(
                f"CAR header nested deeper than {MAX_HEADER_DEPTH} levels at byte {self.pos}"
            )
        major, value, at = self._head()
        if major == 0:
            return value
        if major in (2, 3):
            if value > len(self.data) - self.pos:
                raise CarError(f"truncated CAR header: a {value}-byte string at byte {at}")
            raw = self.data[self.pos : self.pos + value]
            self.pos += value
            if major == 2:
                return raw
            try:
                return raw.decode()
            except UnicodeDecodeError as exc:
                raise CarError(f"CAR header byte {at}: a string that is not UTF-8") from exc
        if major == 4:
            return [self.item(depth + 1) for _ in range(self._count(value, at))]
        if major == 5:
            entries: dict[str, object] = {}
            for _ in range(self._count(value, at)):
                key_at = self.pos
                key = self.item(depth + 1)
                if not isinstance(key, str):
                    raise CarError(f"CAR header byte {key_at}: dag-cbor map keys are strings")
                if key in entries:
                    raise CarError(f"CAR header byte {key_at}: the key {key[:64]!r} repeats")
                entries[key] = self.item(depth + 1)
            return entries
        if major == 6 and value == CID_TAG:
            tagged = self.item(depth + 1)
            if not isinstance(tagged, bytes) or tagged[:1] != b"\x00":
                raise CarError(
                    f"CAR header byte {at}: a CID tag without a 0x00-prefixed byte string"
                )
            try:
                return CID.from_bytes(tagged[1:])
            except CIDError as exc:
                raise CarError(f"CAR header byte {at}: invalid root: {exc}") from exc
        raise CarError(f"CAR header byte {at}: unexpected CBOR major type {major}")


class _Stream:
    """A byte source that counts what it has given, so errors can say where in the CAR."""

    def __init__(self, source: ByteSource) -> None:
        self.source = source
        self.offset = 0

    def varint(self) -> int | None:
        """A multiformats varint (at most 9 bytes, minimal); ``None`` at a clean end."""
        at = self.offset
        value = shift = 0
        for index in range(MAX_VARINT_BYTES):
            byte = self.source.read(1)
            if not byte:
                if index == 0:
                    return None
                raise CarError(f"truncated CAR: the varint at byte {at} ends early")
            self.offset += 1
            value |= (byte[0] & 0x7F) << shift
            if not byte[0] & 0x80:
                if byte[0] == 0 and index:
                    raise CarError(f"CAR varint at byte {at} is not minimally encoded")
                return value
            shift += 7
        raise CarError(f"CAR varint at byte {at} is longer than {MAX_VARINT_BYTES} bytes")

    def exactly(self, size: int) -> bytes:
        data = self.source.read(size)
        if len(data) != size:
            raise CarError(
                f"truncated CAR: {size} bytes due at byte {self.offset}, {len(data)} there"
            )
        self.offset += size
        return data


class CarReader:
    """Iterate the verified blocks of a CARv1 stream; ``roots`` is read at construction."""

    def __init__(self, stream: ByteSource, *, max_section: int = MAX_SECTION_BYTES) -> None:
        self.stream = _Stream(stream)
        self.max_section = max_section
        size = self.stream.varint()
        if size is None or size == 0:
            raise CarError("missing CAR header")
        if size > MAX_HEADER_BYTES:
            raise CarError(f"a CAR header of {size} bytes, more than {MAX_HEADER_BYTES}")
        cbor = _Cbor(self.stream.exactly(size))
        header = cbor.item()
        if cbor.pos != size:
            raise CarError(f"{size - cbor.pos} bytes after the CAR header's CBOR item")
        if not isinstance(header, dict) or header.get("version") != 1:
            raise CarError("not a CARv1 header (version must be 1)")
        roots = header.get("roots")
        if not isinstance(roots, list) or not all(isinstance(r, CID) for r in roots):
            raise CarError("CAR header roots must be a list of CIDs")
        self.roots: list[CID] = roots

    def __iter__(self) -> Iterator[Block]:
        while True:
            at = self.stream.offset
            size = self.stream.varint()
            if size is None:
                return
            if size > self.max_section:
                raise CarError(
                    f"CAR section at byte {at} of {size} bytes exceeds {self.max_section}"
                )
            section = self.stream.exactly(size)
            try:
                cid, start = CID.read(section, 0)
                cid.verify(memoryview(section)[start:])
            except CIDError as exc:
                raise CarError(f"bad block in the CAR section at byte {at}: {exc}") from exc
            yield Block(cid, section[start:])
