"""CARs: the transport of DAGs between robocloud and the IPFS ecosystem.

A CARv1 is a varint-framed dag-cbor header ``{"roots": [...], "version": 1}`` followed by
varint-framed ``(CID, block)`` sections. The reader verifies every block against its CID as
it streams past, so a CAR from anywhere can be trusted block by block.

The reader also takes a CARv2 (https://ipld.io/specs/transport/car/carv2/), as kubo's
``dag import`` does: the 11-byte pragma, a 40-byte header (characteristics, data offset, data
size, index offset), then a CARv1 payload at the data offset, which is read with every bound
of a CARv1 and no further than the data size. The index is never read: import needs none, and
nothing in it is trusted. The writer writes CARv1 only, as kubo's ``dag export`` does.
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

CARV2_PRAGMA = bytes.fromhex("0aa16776657273696f6e02")
"""The varint 10 and the dag-cbor ``{"version": 2}``: a CARv1 header a CARv1 reader refuses."""
CARV2_HEADER_BYTES = 40
CARV2_PREFIX_BYTES = len(CARV2_PRAGMA) + CARV2_HEADER_BYTES
"""51: where a CARv2's payload may start at the earliest."""
CARV2_CHARACTERISTICS = {
    0: "fully-indexed",
    1: "dfs-order",
    2: "duplicates",
    3: "no-duplicates",
    4: "zero-terminated-payload",
    5: "trailer-message",
}
"""The characteristics the CARv2 spec defines, by bit: bit 0 is the left-most bit of the
first byte (go-car's ``fullyIndexedCharPos``, bit 7 of its little-endian ``Hi``).

Bits 0-3 and 5 describe the index, the order of blocks, duplicates, or bytes after the
payload, none of which an import reads: they are taken. Bit 4 (a payload that ends at a
zero-length section rather than at the data size) is refused, as go-car (kubo) cannot read it
either; 2 and 3 together are refused as the spec calls them exclusive; any other bit is
refused, because a future characteristic may move the payload (as bit 4 does) and reading it
as if it were unset could import something other than what the writer meant."""
_SKIP_CHUNK = 1 << 16


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

    def __init__(self, source: ByteSource, offset: int = 0, end: int | None = None) -> None:
        self.source = source
        self.offset = offset
        self.cut = "" if end is None else f" (the CARv2 data size ends the payload at byte {end})"

    def varint(self) -> int | None:
        """A multiformats varint (at most 9 bytes, minimal); ``None`` at a clean end."""
        at = self.offset
        value = shift = 0
        for index in range(MAX_VARINT_BYTES):
            byte = self.source.read(1)
            if not byte:
                if index == 0:
                    return None
                raise CarError(f"truncated CAR: the varint at byte {at} ends early{self.cut}")
            self.offset += 1
            value |= (byte[0] & 0x7F) << shift
            if not byte[0] & 0x80:
                if byte[0] == 0 and index:
                    raise CarError(f"CAR varint at byte {at} is not minimally encoded")
                return value
            shift += 7
        raise CarError(f"CAR varint at byte {at} is longer than {MAX_VARINT_BYTES} bytes")

    def exactly(self, size: int, what: str = "CAR") -> bytes:
        """``size`` bytes, or a :class:`CarError` naming ``what`` was cut short and where."""
        data = self.source.read(size)
        if len(data) != size:
            raise CarError(
                f"truncated {what}: {size} bytes due at byte {self.offset}, {len(data)} there"
                f"{self.cut}"
            )
        self.offset += size
        return data


class _Payload:
    """A CARv2's CARv1 payload: ``size`` bytes of ``source`` starting at file byte ``start``.

    Gives nothing past the data size, and refuses a CAR that ends before it, so the payload's
    own reader sees a clean end only where the data size says the payload ends."""

    def __init__(self, source: ByteSource, start: int, size: int) -> None:
        self.source = source
        self.start = start
        self.size = size
        self.given = 0

    def read(self, size: int = -1, /) -> bytes:
        left = self.size - self.given
        wanted = left if size < 0 else min(size, left)
        data = b""
        while len(data) < wanted:
            more = self.source.read(wanted - len(data))
            if not more:
                raise CarError(
                    f"CARv2 data size {self.size} runs past the end of the CAR: the payload "
                    f"from byte {self.start} would end at byte {self.start + self.size}, the "
                    f"CAR ends at byte {self.start + self.given + len(data)}"
                )
            data += more
        self.given += len(data)
        return data


def _read_header(stream: _Stream) -> tuple[object, bytes]:
    """A CAR header at ``stream``'s offset: its decoded CBOR item and its raw bytes."""
    size = stream.varint()
    if size is None or size == 0:
        raise CarError(f"missing CAR header at byte {stream.offset}")
    if size > MAX_HEADER_BYTES:
        raise CarError(f"a CAR header of {size} bytes, more than {MAX_HEADER_BYTES}")
    raw = stream.exactly(size)
    cbor = _Cbor(raw)
    header = cbor.item()
    if cbor.pos != size:
        raise CarError(f"{size - cbor.pos} bytes after the CAR header's CBOR item")
    return header, raw


def _version(header: object) -> object:
    return header.get("version") if isinstance(header, dict) else None


def _check_characteristics(field: bytes) -> None:
    bits = [bit for bit in range(8 * len(field)) if field[bit // 8] & (0x80 >> (bit % 8))]
    unknown = [bit for bit in bits if bit not in CARV2_CHARACTERISTICS]
    if unknown:
        shown = ", ".join(map(str, unknown[:8])) + (", ..." if len(unknown) > 8 else "")
        raise CarError(
            f"unknown CARv2 characteristics bits set: {shown} (the spec defines bits 0-5; an "
            f"unknown one may change where the payload is, so it is not ignored)"
        )
    if 4 in bits:
        raise CarError(
            "CARv2 characteristic bit 4 (zero-terminated-payload) is not supported: the "
            "payload must end at its data size"
        )
    if 2 in bits and 3 in bits:
        raise CarError(
            "CARv2 characteristics bits 2 (duplicates) and 3 (no-duplicates) are both set; "
            "the spec makes them exclusive"
        )


def _open_v2(outer: _Stream) -> _Stream:
    """Read a CARv2's header after its pragma and skip to its payload; the payload's stream."""
    fixed = outer.exactly(CARV2_HEADER_BYTES, "CARv2 header")
    _check_characteristics(fixed[:16])
    offset, size, index = (int.from_bytes(fixed[at : at + 8], "little") for at in (16, 24, 32))
    if offset < CARV2_PREFIX_BYTES:
        raise CarError(
            f"CARv2 data offset {offset} is inside the pragma and header, which end at byte "
            f"{CARV2_PREFIX_BYTES}"
        )
    if size == 0:
        raise CarError("CARv2 data size 0: the CAR has no CARv1 payload")
    if 0 < index < offset + size:
        raise CarError(
            f"CARv2 index offset {index} is inside the payload (bytes {offset} to "
            f"{offset + size}); an index follows the payload"
        )
    while outer.offset < offset:
        skipped = len(outer.source.read(min(_SKIP_CHUNK, offset - outer.offset)))
        if not skipped:
            raise CarError(
                f"CARv2 data offset {offset} is beyond the end of the CAR at byte {outer.offset}"
            )
        outer.offset += skipped
    return _Stream(_Payload(outer.source, offset, size), offset, offset + size)


class CarReader:
    """Iterate the verified blocks of a CARv1 or CARv2 stream; ``roots`` is read at
    construction, ``version`` says which. The stream is read once, from its start; a CARv2's
    is read no further than its payload's end, so its index (or whatever follows) is never
    read, and is bounded only by whatever bounds the stream (an upload's own limit).

    Without ``carv2`` a CARv2 is refused at its pragma, before any padding is read: the
    padding before a CARv2's payload is read and discarded, so a stream with no bound of its
    own (a gateway's answer) that declares a data offset of 2^63 would be read forever with
    nothing to show for it, whatever the caller's bound on the file."""

    def __init__(
        self, stream: ByteSource, *, max_section: int = MAX_SECTION_BYTES, carv2: bool = True
    ) -> None:
        self.stream = _Stream(stream)
        self.max_section = max_section
        self.version = 1
        header, raw = _read_header(self.stream)
        if _version(header) == 2:
            if not carv2:
                raise CarError("a CARv2, where only a CARv1 is read")
            if encode_varint(len(raw)) + raw != CARV2_PRAGMA:
                raise CarError(
                    f"a version 2 CAR header that is not the CARv2 pragma {CARV2_PRAGMA.hex()}"
                )
            self.version = 2
            self.stream = _open_v2(self.stream)
            at = self.stream.offset
            header, _ = _read_header(self.stream)
            if _version(header) != 1:
                raise CarError(
                    f"the CARv2 payload at byte {at} is not a CARv1 (its header's version "
                    f"must be 1)"
                )
        elif _version(header) != 1:
            raise CarError("not a CARv1 or CARv2 header (version must be 1 or 2)")
        roots = header.get("roots") if isinstance(header, dict) else None
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
